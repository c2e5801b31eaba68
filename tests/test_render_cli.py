"""`prt render`: transfer files of every kind relit and rendered (GLSL and CPU decode), checked against the
analytic value and against each other."""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from prt_torch.cli import main


@pytest.fixture(scope="module")
def transfer_file(tmp_path_factory):
    from prt_torch.scene import builtin
    from prt_torch.transfer import Transfer, unshadowed_transfer

    mesh = builtin("convex", size="small").with_albedo([0.2, 0.5, 0.8])
    t = Transfer("diffuse", unshadowed_transfer(mesh.normals, 3).float(), mesh, {"bands": 3, "albedo_folded": False})
    path = tmp_path_factory.mktemp("cli") / "convex.prt"
    t.save(path)
    return path


def _read(path):
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    arr = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, "float")).reshape(spec.height, spec.width, -1)
    inp.close()
    return arr


def test_constant_light_renders_albedo(transfer_file, tmp_path, capsys):
    """Unshadowed diffuse transfer under uniform radiance 1 gives L_out = ρ at every vertex
    (transfer/diffuse.py normalisation, l_00 = 2√π), so every covered pixel shows the albedo."""
    out = tmp_path / "c.exr"
    rc = main(["render", str(transfer_file), "--light", "constant:value=1", "-o", str(out), "--width", "40",
               "--height", "32", "--background", "-1", "--supersample", "1"])
    assert rc == 0, capsys.readouterr().err
    img = _read(out)
    assert img.shape == (32, 40, 3)
    covered = img[:, :, 0] != -1
    assert covered.sum() > 200
    assert np.abs(img[covered] - [0.2, 0.5, 0.8]).max() < 1e-5
    png = tmp_path / "c.png"
    assert main(["render", str(transfer_file), "-o", str(png), "--width", "24", "--height", "24",
                 "--orthographic", "--light", "sky"]) == 0
    assert png.stat().st_size > 0


def test_cli_errors(transfer_file, tmp_path, capsys):
    out = tmp_path / "x.png"
    out.write_bytes(b"")
    assert main(["render", str(transfer_file), "-o", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["render", str(transfer_file), "-o", str(tmp_path / "x.jpg")]) == 2
    assert "accepted extensions" in capsys.readouterr().err
    assert main(["render", str(transfer_file), "-o", str(tmp_path / "y.png"), "--compare", str(tmp_path / "z.exr")]) == 2
    assert ".png" in capsys.readouterr().err
    assert main(["render", str(tmp_path / "missing.prt"), "-o", str(tmp_path / "y.png")]) == 2
    assert main(["render", str(transfer_file), "-o", str(tmp_path / "y.png"), "--exposure", "bright"]) == 2
    if importlib.util.find_spec("prt_torch.codecs") is None:
        assert main(["render", str(transfer_file), "-o", str(tmp_path / "y.png"), "--codec-file", "c.prt"]) == 2
        assert "prt_torch.codecs" in capsys.readouterr().err
    assert not (tmp_path / "y.png").exists()


def test_codec_file_compare(transfer_file, tmp_path):
    codecs = pytest.importorskip("prt_torch.codecs")
    from prt_torch.transfer import Transfer

    t = Transfer.load(transfer_file)
    codec = codecs.get("vq", clusters=8) if "vq" in codecs.available() else None
    if codec is None:
        pytest.skip("no 'vq' codec registered")
    X = t.signal()
    codec.fit(X)
    cfile = tmp_path / "vq.prt"
    codec.save(cfile, codec.encode(X))
    out, cmp_, ref = tmp_path / "vq.exr", tmp_path / "cmp.png", tmp_path / "ref.exr"
    common = ["--width", "32", "--height", "32", "--light", "directional:direction=1,0,1", "--supersample", "1"]
    rc = main(["render", str(transfer_file), "--codec-file", str(cfile), "-o", str(out), "--compare", str(cmp_), *common])
    assert rc == 0 and out.exists() and cmp_.exists()
    assert main(["render", str(transfer_file), "-o", str(ref), *common]) == 0
    # VQ with 8 clusters quantises the normals' transfer: its render differs from the uncompressed one
    a, b = _read(out), _read(ref)
    assert np.abs(a - b).max() > 1e-2


@pytest.fixture(scope="module")
def kind_files(tmp_path_factory):
    """Glossy [V, 9, 16] and MRT [V, 36, 16] transfer files (synthetic transfer-like data on a real
    mesh) and a codec file for each."""
    from prt_torch import codecs
    from prt_torch.codecs.synthetic import transfer_like
    from prt_torch.scene import builtin
    from prt_torch.transfer import Transfer

    mesh = builtin("bumpy_sphere", size="small")
    V = mesh.num_vertices
    d = tmp_path_factory.mktemp("kinds")
    out = {}
    for kind, n_out, name, kw in (("glossy", 9, "cpca", dict(clusters=4, vectors=3)), ("mrt", 36, "mrt_pca", dict(vectors=6))):
        t = Transfer(kind, transfer_like(V, n_out, 16, seed=3).view(V, n_out, 16), mesh,
                     {"matrix_shape": [n_out, 16], **({"out_index": list(range(9))} if kind == "glossy" else {})})
        t.save(d / f"{kind}.prt")
        c = codecs.get(name, **kw).fit(t.signal(), matrix_shape=(n_out, 16))
        c.save(d / f"{kind}.{name}.prt", c.encode(t.signal()), extra_meta={"mesh_hash": mesh.content_hash()})
        out[kind] = (d / f"{kind}.prt", d / f"{kind}.{name}.prt")
    return out


@pytest.mark.parametrize("kind", ["glossy", "mrt"])
def test_view_dependent_kinds_glsl_equals_cpu(kind_files, kind, tmp_path, capsys):
    tfile, cfile = kind_files[kind]
    common = ["--width", "48", "--height", "40", "--supersample", "1", "--light", "sky"]
    for codec in ([], ["--codec-file", str(cfile)]):
        g, c = tmp_path / "g.exr", tmp_path / "c.exr"
        assert main(["render", str(tfile), *codec, "--decode", "glsl", "-o", str(g), "--overwrite", *common]) == 0
        assert main(["render", str(tfile), *codec, "--decode", "cpu", "-o", str(c), "--overwrite", *common]) == 0
        a, b = _read(g), _read(c)
        m = np.abs(b).sum(2) > 0
        assert m.sum() > 200
        mse = float(np.mean((a[m] - b[m]) ** 2))
        assert mse == 0 or 10 * np.log10(np.abs(b[m]).max() ** 2 / mse) > 50
    capsys.readouterr()
    cmp_ = tmp_path / "cmp.png"
    rc = main(["render", str(tfile), "--codec-file", str(cfile), "-o", str(tmp_path / "x.png"), "--compare", str(cmp_),
               "--validate", *common])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "GLSL vs CPU:" in text and "-> ok" in text
    assert cmp_.exists() and cmp_.with_suffix(".exr").exists()
    comp = _read(cmp_.with_suffix(".exr"))
    assert comp.shape[0] == 40 and comp.shape[1] == 3 * 48 + 2 * 4


def test_codec_file_of_another_transfer_is_refused(kind_files, transfer_file, tmp_path, capsys):
    _, glossy_codec = kind_files["glossy"]
    mrt_file, _ = kind_files["mrt"]
    assert main(["render", str(mrt_file), "--codec-file", str(glossy_codec), "-o", str(tmp_path / "x.png")]) == 2
    assert "does not belong" in capsys.readouterr().err
    assert main(["render", str(transfer_file), "--codec-file", str(glossy_codec), "-o", str(tmp_path / "x.png")]) == 2
    assert "hash" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_render_transport_tables_and_gaussian_codec_file(tmp_path, capsys):
    """`prt render TABLE_DIR --codec-file gaussian.prt`: the shader's prefiltered lookups against
    the CPU engine (GLSL vs CPU above 50 dB, same coverage); uncompressed tables render on the CPU
    and their GLSL decode is refused by name."""
    import re
    import warnings

    from prt_torch.cli import main

    table = tmp_path / "table"
    assert main(["precompute", "convex", "--kind", "transport", "--views", "1", "--cube-res", "4", "--brdf", "phong",
                 "--brdf-param", "s=8", "--no-progress", "-o", str(table)]) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["compress", str(table), "--codec", "gaussian", "--param", "lobes=1", "--param", "max_iter=5",
                     "-o", str(tmp_path / "g.prt")]) == 0
    capsys.readouterr()
    assert main(["render", str(table), "--codec-file", str(tmp_path / "g.prt"), "--decode", "glsl", "--validate",
                 "--width", "96", "--height", "96", "-o", str(tmp_path / "g.png")]) == 0
    m = re.search(r"GLSL vs CPU: ([\d.]+) dB \(same coverage: yes", capsys.readouterr().out)
    assert m and float(m.group(1)) > 50
    assert main(["render", str(table), "--decode", "cpu", "--width", "64", "--height", "64", "-o", str(tmp_path / "u.png")]) == 0
    assert main(["render", str(table), "--decode", "glsl", "-o", str(tmp_path / "u2.png")]) == 2
    assert "no GLSL decoder" in capsys.readouterr().err
