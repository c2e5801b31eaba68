"""An offscreen OpenGL context through pyrender's EGL platform (Mesa llvmpipe where there is no GPU).

* ``PYOPENGL_PLATFORM`` should be ``egl`` before PyOpenGL is first imported; this module sets it
  (``os.environ.setdefault``). pyrender pins PyOpenGL 3.1.0, whose OSMesa path does not work, so
  EGL is the only supported platform (pyrender's EGL module switches an already-loaded PyOpenGL
  to EGL; a failure names the platform in use).
* The display is Mesa's surfaceless platform where available (our own display, unaffected by
  other EGL users), else pyrender's default EGL device.
* One context per process, shared by every :class:`~prt_torch.render.Renderer` and reference
  counted: it is created by the first :func:`acquire` and destroyed by the last :func:`release`.
  (pyrender's own ``EGLPlatform.delete_context`` also calls ``eglTerminate`` on the display,
  which Mesa shares between contexts of the same device; the subclass below only destroys its
  context, so other EGL users in the process are unaffected.)
* Every GL call is made with the context current on the calling thread, under :data:`LOCK`.

Nothing here is imported by ``import prt_torch.render``: OpenGL is loaded on first use, so the
image helpers (heat maps, PNG/EXR writers) work on machines without EGL.
"""
from __future__ import annotations

import os
import sys
import threading

__all__ = ["RenderUnavailable", "acquire", "release", "make_current", "gl_info", "LOCK", "INSTALL_HINT"]

INSTALL_HINT = (
    "offscreen rendering needs EGL with Mesa: set PYOPENGL_PLATFORM=egl before anything imports "
    "OpenGL, and install the Debian packages libegl1 libegl-mesa0 libgl1-mesa-dri "
    "(`sudo apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri`, done by scripts/setup)"
)

LOCK = threading.RLock()

_state: dict = {"platform": None, "refs": 0, "info": None}


class RenderUnavailable(RuntimeError):
    """No usable OpenGL context (EGL missing, wrong PYOPENGL_PLATFORM, GL too old)."""


def _platform_note() -> str:
    plat = os.environ.get("PYOPENGL_PLATFORM", "")
    gl_platform = sys.modules.get("OpenGL.platform")
    current = type(getattr(gl_platform, "PLATFORM", None)).__name__ if gl_platform is not None else "not loaded"
    return f"PYOPENGL_PLATFORM={plat!r}, PyOpenGL platform {current}"


class _SurfacelessDevice:
    """An ``EGLDevice`` stand-in for pyrender's ``EGLPlatform`` giving Mesa's surfaceless display
    (EGL_MESA_platform_surfaceless): a display of our own, so that another EGL user terminating
    the device display (``pyrender.OffscreenRenderer.delete`` calls ``eglTerminate``) does not
    take our context with it."""

    name = "mesa-surfaceless"

    def get_display(self):
        import pyrender.platforms.egl as pe

        return pe._eglGetPlatformDisplayEXT(EGL_PLATFORM_SURFACELESS_MESA, None, None)


EGL_PLATFORM_SURFACELESS_MESA = 0x31DD


def _display_source():
    """Mesa's surfaceless platform when the EGL client advertises it, else pyrender's default
    device (e.g. NVIDIA's EGL device platform)."""
    import pyrender.platforms.egl as pe
    from OpenGL import EGL

    try:
        ext = EGL.eglQueryString(EGL.EGL_NO_DISPLAY, EGL.EGL_EXTENSIONS) or b""
    except Exception:  # EGL_EXT_client_extensions missing: the query itself fails
        ext = b""
    if b"EGL_MESA_platform_surfaceless" in ext and pe._eglGetPlatformDisplayEXT is not None:
        return _SurfacelessDevice()
    return pe.get_default_device()


def _create():
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    try:
        from pyrender.platforms.egl import EGLPlatform
    except Exception as e:  # ImportError, RuntimeError('EGL platform plugin is not available'), OSError
        raise RenderUnavailable(f"cannot load pyrender's EGL platform ({type(e).__name__}: {e}; {_platform_note()}); "
                                f"{INSTALL_HINT}") from e

    class _SharedEGL(EGLPlatform):
        def delete_context(self):  # destroy our context only; leave the shared display initialised
            from OpenGL.EGL import EGL_NO_CONTEXT, EGL_NO_SURFACE, eglDestroyContext, eglMakeCurrent

            if self._egl_display is not None and self._egl_context is not None:
                eglMakeCurrent(self._egl_display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
                eglDestroyContext(self._egl_display, self._egl_context)
            self._egl_context = None

    try:
        plat = _SharedEGL(1, 1, device=_display_source())
        plat.init_context()
        from OpenGL import GL

        version = GL.glGetString(GL.GL_VERSION)
        renderer = GL.glGetString(GL.GL_RENDERER)
        major = int(GL.glGetIntegerv(GL.GL_MAJOR_VERSION))
        minor = int(GL.glGetIntegerv(GL.GL_MINOR_VERSION))
    except RenderUnavailable:
        raise
    except Exception as e:  # AssertionError from pyrender's asserts, GLError, EGLError, OSError
        raise RenderUnavailable(f"cannot create an EGL OpenGL context ({type(e).__name__}: {e or 'EGL call failed'}; "
                                f"{_platform_note()}); "
                                f"{INSTALL_HINT}") from e
    if (major, minor) < (4, 1):
        plat.delete_context()
        raise RenderUnavailable(f"OpenGL {major}.{minor} context; prt_torch.render needs 4.1 core. {INSTALL_HINT}")
    _state["info"] = {
        "renderer": renderer.decode() if isinstance(renderer, bytes) else str(renderer),
        "version": version.decode() if isinstance(version, bytes) else str(version),
        "max_texture_size": int(GL.glGetIntegerv(GL.GL_MAX_TEXTURE_SIZE)),
        "max_texture_buffer_size": int(GL.glGetIntegerv(GL.GL_MAX_TEXTURE_BUFFER_SIZE)),
        "max_vertex_attribs": int(GL.glGetIntegerv(GL.GL_MAX_VERTEX_ATTRIBS)),
        "max_renderbuffer_size": int(GL.glGetIntegerv(GL.GL_MAX_RENDERBUFFER_SIZE)),
    }
    return plat


def acquire():
    """Take a reference on the shared context (creating it on first use) and make it current.

    Raises :class:`RenderUnavailable` with installation hints when no context can be made."""
    with LOCK:
        if _state["platform"] is None:
            _state["platform"] = _create()
        _state["refs"] += 1
        _state["platform"].make_current()
        return _state["platform"]


def make_current() -> None:
    """Make the shared context current on this thread (call under :data:`LOCK`)."""
    plat = _state["platform"]
    if plat is None:
        raise RenderUnavailable("no OpenGL context: the renderer was closed")
    plat.make_current()


def release() -> None:
    """Drop a reference; the last one destroys the context (GL objects must be deleted first)."""
    with LOCK:
        if _state["refs"] <= 0:
            return
        _state["refs"] -= 1
        if _state["refs"] == 0 and _state["platform"] is not None:
            try:
                _state["platform"].delete_context()
            finally:
                _state["platform"] = None


def gl_info() -> dict:
    """Renderer string, GL version and limits of the shared context (creates it if needed)."""
    with LOCK:
        if _state["info"] is None or _state["platform"] is None:
            acquire()
            info = dict(_state["info"])
            release()
            return info
        return dict(_state["info"])
