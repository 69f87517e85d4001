"""The package as a wheel installs it: built, installed into a new virtual environment outside
the checkout, and used from another folder, with its configs as package data."""

import shutil
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Run by the wheel's interpreter, from a folder that holds nothing of the checkout.
CHECK = """
import sys
from pathlib import Path
import mixnerf_eqx as mx
here = Path(mx.__file__).resolve().parent
assert here.is_relative_to(Path(sys.prefix).resolve()), here  # the new environment's copy
names = mx.config.config_names()
assert "builtin_grid" in names and "llff3" in names, names
for name in names:
    config = mx.load_config(name)  # every packaged config, `extends` included
    assert config.name, name
print(len(names), "configs")
"""


@pytest.mark.slow
def test_a_wheel_installed_elsewhere_has_its_configs_and_trains(tmp_path):
    # Built from a copy of what the wheel is made of, so that the build leaves nothing in the checkout.
    source = tmp_path / "source"
    shutil.copytree(
        REPO / "mixnerf_eqx", source / "mixnerf_eqx", ignore=shutil.ignore_patterns("__pycache__")
    )
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, source / name)
    wheels = tmp_path / "wheels"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "-w",
            str(wheels),
            str(source),
        ],
        check=True,
        capture_output=True,
    )
    (wheel,) = wheels.glob("mixnerf_eqx-*.whl")
    environment = tmp_path / "env"
    venv.create(environment, with_pip=False)
    python = environment / "bin" / "python"
    site = Path(
        subprocess.run(
            [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
    )
    # The dependencies come from this interpreter's environment (a path in a .pth file: its own
    # .pth files, such as an editable install's finder, are not read); the package from the wheel.
    ours = sysconfig.get_paths()
    (site / "dependencies.pth").write_text("".join(f"{ours[kind]}\n" for kind in ("purelib", "platlib")))
    subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-deps", str(wheel)],
        check=True,
        capture_output=True,
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    def run(*arguments: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [str(python), *arguments], cwd=elsewhere, capture_output=True, text=True, timeout=600
        )

    checked = run("-c", CHECK)
    assert checked.returncode == 0, checked.stderr
    assert f"{len(list((REPO / 'configs').glob('*.toml')))} configs" in checked.stdout
    usage = run("-m", "mixnerf_eqx.train", "--help")
    assert usage.returncode == 0 and "--config" in usage.stdout
    # The default command (the packaged builtin_grid config), a few steps of a small model.
    steps = ["train.max_steps=3", "data.resolution=32", "data.num_test_views=1", "train.eval_every=0"]
    steps += ["grid.levels=2", "grid.min_resolution=8", "grid.max_resolution=16", "train.batch_size=64"]
    trained = run("-m", "mixnerf_eqx.train", "--no-progress", "--run-dir", "run", *steps)
    assert trained.returncode == 0, trained.stderr[-3000:]
    assert "config builtin_grid" in trained.stdout and (elsewhere / "run" / "metrics.json").is_file()
