"""Shared fixtures."""
import os

import pytest


@pytest.fixture(scope="module")
def renderer(request):
    """One offscreen float renderer per test module, of the module's ``RENDER_SIZE`` (width,
    height). No GL: skipped only with PRT_SKIP_GL=1 outside CI; in CI (CI=true) the test fails."""
    from prt_torch.render import Renderer, RenderUnavailable

    w, h = getattr(request.module, "RENDER_SIZE", (64, 48))
    try:
        r = Renderer(w, h)
    except RenderUnavailable as e:
        if os.environ.get("PRT_SKIP_GL") == "1" and os.environ.get("CI", "").lower() != "true":
            pytest.skip(f"PRT_SKIP_GL=1 and no GL: {e}")
        raise
    yield r
    r.close()
