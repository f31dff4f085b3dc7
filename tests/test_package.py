"""The package installed as a wheel (not editable): its configs ship inside it and its console scripts run."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = ("nvs-train", "nvs-evaluate", "nvs-sweep", "nvs-viewer", "nvs-demo", "nvs-convert", "nvs-render-video",
           "nvs-export-ply", "nvs-figures", "nvs-pareto")


def test_pyproject_lists_the_scripts_and_the_dev_extra_reuses_the_others():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert set(SCRIPTS) <= set(project["scripts"])
    extras = project["optional-dependencies"]
    others = [name for name in extras if name != "dev"]
    assert f"nvs[{','.join(others)}]" in extras["dev"]
    listed = {req for name in others for req in extras[name]}
    assert not listed & set(extras["dev"])  # nothing of another extra listed twice
    assert project["requires-python"] == ">=3.11"  # typing.NotRequired


def _wheel(tmp_path: Path) -> Path:
    """The wheel built from a copy of the sources (the checkout stays free of build/)."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    for name in ("nvs", "conf"):
        shutil.copytree(REPO / name, src / name, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
    out = tmp_path / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out),
                    str(src)], check=True, capture_output=True, timeout=300)
    (wheel,) = out.glob("nvs-*.whl")
    return wheel


def test_the_installed_wheel_trains_from_its_own_configs(objects_root, tmp_path):
    wheel = _wheel(tmp_path)
    names = zipfile.ZipFile(wheel).namelist()
    shipped = {n.removeprefix("nvs/conf/") for n in names if n.startswith("nvs/conf/")}
    assert shipped == {str(p.relative_to(REPO / "conf")) for p in (REPO / "conf").rglob("*.yaml")}

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    # no network: the dependencies are the system site's; the wheel goes into the new environment even though the
    # system site holds an (editable) nvs of the same version
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-index", "--no-deps",
                    "--force-reinstall", "-q", str(wheel)],
                   check=True, capture_output=True, timeout=300)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env['PATH']}"
    work = tmp_path / "work"  # a directory without the checkout: nothing can come from it
    work.mkdir()
    where = subprocess.run([str(python), "-c", "import nvs.run.compose as c; print(c.__file__); print(c.CONF_DIR)"],
                           cwd=work, env=env, capture_output=True, text=True, check=True).stdout.split()
    assert all(Path(p).is_relative_to(venv) for p in where), where

    # the renderer's extracted asset packages: the working directory's data/assets (not a folder inside the venv),
    # and a folder asked for that is missing is one clear error
    found = subprocess.run([str(python), "-c", "from nvs.data.render.sources import asset_dir; print(asset_dir())"],
                           cwd=work, env=env, capture_output=True, text=True, check=True).stdout.strip()
    assert Path(found) == (work / "data" / "assets").resolve(), found
    missing = subprocess.run([str(python), "-m", "nvs.data.render", "chairs", f"assets={work / 'nope'}"], cwd=work,
                             env=env, capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and missing.stderr.startswith(f"error: assets={work / 'nope'}: no such directory")

    helped = subprocess.run(["nvs-train", "--help"], cwd=work, env=env, capture_output=True, text=True, timeout=120)
    assert helped.returncode == 0, helped.stderr[-2000:]
    assert "train is powered by Hydra" in helped.stdout and "experiment: " in helped.stdout
    res = subprocess.run(["nvs-train", f"data.root={objects_root}", f"paths.log_dir={work / 'runs'}",
                          "trainer.max_steps=2", "trainer.val_check_interval=2", "data.loader.batch_size=2",
                          "loss=[recon]", "trainer.precision=32-true", "trainer.enable_progress_bar=false"],
                         cwd=work, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    metrics = json.loads(next((work / "runs").rglob("metrics.json")).read_text())
    assert metrics["steps"] == 2 and metrics["test"]["n_pairs"] == 4
    for script in SCRIPTS:
        assert (venv / "bin" / script).is_file(), script
