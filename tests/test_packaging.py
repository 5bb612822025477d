"""The built wheel installs whole: weights, sample photos and every module, usable from anywhere.

One module-scoped fixture builds the wheel from a copy of the checkout's sources (an in-tree
build could pick up stale files from ``build/``), installs it with ``--no-deps`` into a fresh
virtual environment that sees this environment's packages (torch, gradio, ...) through a
``.pth`` line but not its editable ``d2f``, and the tests then run that environment's Python
and its ``d2f`` script from a folder outside the checkout.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import site
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = [f"samples/{p.name}" for p in sorted((ROOT / "assets" / "samples").iterdir())]
#: the network, the scene teachers' weights with their notice and licence texts, the samples
SHIPPED = (
    ["weights/d2f_lite.pt"]
    + [
        f"weights/{p.name}"
        for p in sorted((ROOT / "assets" / "weights").iterdir())
        if p.name.startswith(("teacher_", "TEACHERS", "LICENSE"))
    ]
    + SAMPLES
)

pytestmark = pytest.mark.slow


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _run(cmd: list[str], cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "D2F_"))}
    env["GRADIO_ANALYTICS_ENABLED"] = "False"
    out = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, f"{cmd} failed:\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    return out


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    pytest.importorskip("setuptools", minversion="68", reason="builds without build isolation")
    src = tmp_path_factory.mktemp("src")
    junk = shutil.ignore_patterns("__pycache__", "*.pyc", "charts")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    for name in ("d2f_core", "app", "assets"):
        shutil.copytree(ROOT / name, src / name, ignore=junk)
    dist = tmp_path_factory.mktemp("dist")
    _run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index"]
        + ["-q", "-w", str(dist), str(src)],
        cwd=src,
    )
    (found,) = dist.glob("d2f-*.whl")
    return found


@pytest.fixture(scope="module")
def venv(wheel, tmp_path_factory) -> Path:
    """A fresh venv holding the wheel, with this environment's site-packages on its path."""
    env_dir = tmp_path_factory.mktemp("venv")
    _run([sys.executable, "-m", "venv", "--without-pip", str(env_dir)], cwd=env_dir)
    python = env_dir / "bin" / "python"
    _run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "-q"]
        + ["--no-deps", "--no-index", str(wheel)],
        cwd=env_dir,
    )
    purelib = _run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        cwd=env_dir,
    ).stdout.strip()
    # a line of a .pth file only adds its folder to sys.path: that folder's own .pth files
    # (this environment's editable d2f finder) are not run, so d2f comes from the wheel
    ours = [p for p in [*site.getsitepackages(), sysconfig.get_paths()["purelib"]] if p]
    Path(purelib, "_test_base_packages.pth").write_text("\n".join(dict.fromkeys(ours)) + "\n")
    return env_dir


def test_wheel_holds_every_module_and_the_shipped_files(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    modules = {
        p.relative_to(ROOT).as_posix()
        for top in ("d2f_core", "app")
        for p in (ROOT / top).rglob("*.py")
        if "__pycache__" not in p.parts
    }
    assert modules, "no modules found in the checkout"
    assert not modules - names, f"modules missing from the wheel: {sorted(modules - names)}"
    with zipfile.ZipFile(wheel) as z:
        for rel in SHIPPED:
            data = z.read(f"d2f_core/assets/{rel}")
            assert _sha(data) == _sha((ROOT / "assets" / rel).read_bytes()), rel
    # the README's charts are for the repository, not the package
    assert not [n for n in names if n.startswith("d2f_core/assets/charts/")]
    assert not [n for n in names if n.startswith(("tests/", "assets/"))]


def test_wheel_holds_the_package_weights_and_samples_only(wheel):
    """No frozen renderer, no benchmark-only data: the code of d2f_core and app, the
    weights, the sample photos and the assets' README, nothing else."""
    names = zipfile.ZipFile(wheel).namelist()
    assert not [n for n in names if "benchmarks/" in n or "bench_baseline" in n or "00e22a4" in n]
    frozen = []
    with zipfile.ZipFile(wheel) as z:
        for n in names:
            if n.endswith(".py") and b"frozen copy" in z.read(n).lower():
                frozen.append(n)
    assert not frozen, f"frozen code in the wheel: {frozen}"
    shipped = {"README.md", "__init__.py", *SHIPPED}
    extra = []
    for n in names:
        top = n.split("/")[0]
        if top.endswith(".dist-info"):
            continue
        if n.startswith("d2f_core/assets/"):
            if n[len("d2f_core/assets/") :] not in shipped:
                extra.append(n)
        elif top not in ("d2f_core", "app") or not n.endswith((".py", ".md")):
            extra.append(n)
    assert not extra, f"the wheel carries more than the package: {extra}"


def test_installed_wheel_loads_weights_and_renders_a_sample(venv, tmp_path):
    code = f"""
import pathlib, sys
import numpy as np
import d2f_core
from d2f_core import D2F, bundled
from d2f_core.io import load_image
here = pathlib.Path(d2f_core.__file__).resolve()
assert pathlib.Path({str(venv)!r}).resolve() in here.parents, here
assert pathlib.Path({str(ROOT)!r}).resolve() not in here.parents, here
weights = bundled.shipped_weights()
assert pathlib.Path({str(venv)!r}).resolve() in weights.resolve().parents, weights
model = D2F.from_pretrained()
photos = bundled.sample_photos()
assert [p.name for p in photos] == {[p.split("/")[1] for p in SAMPLES]!r}, photos
image = load_image(photos[0])
scene = model.prepare(image)
result = model.render(scene, model.focus_at(scene, 10, 10), 20.0)
assert result.bokeh.shape == image.shape and np.isfinite(result.bokeh).all()
assert np.abs(result.bokeh - image).mean() > 1e-3  # something was blurred
# the scene source: the teachers' ports and their weights, with nothing but torch
scene = model.prepare(image, depth="scene")
assert scene.disparity_source == "scene", scene.disparity_source
assert "objects" in scene.disparity_output, scene.disparity_output
import app.main
import app.panels
assert app.panels.sample_paths() == [str(p) for p in photos]
demo = app.main.build_demo(model)  # the page with its examples, not launched
assert type(demo).__name__ == "Blocks"
print("ok", weights)
"""
    out = _run([str(venv / "bin" / "python"), "-I", "-c", code], cwd=tmp_path)
    assert out.stdout.startswith("ok ")


def test_installed_cli_renders_a_sample_from_another_folder(venv, tmp_path):
    sample = ROOT / "assets" / "samples" / "chelsea.jpg"
    target = tmp_path / "out.png"
    _run(
        [str(venv / "bin" / "d2f"), "render", str(sample), "--blur", "16"]
        + ["--quality", "fast", "-q", "-o", str(target)],
        cwd=tmp_path,
    )
    from d2f_core.io import load_image

    out, photo = load_image(target), load_image(sample)
    assert out.shape == photo.shape
    assert abs(out.astype(float) - photo.astype(float)).mean() > 1e-3
