"""The package installed away from any checkout (``pip install ./python``): used from another
directory, FormationEnv finds the binaries as an installed tool does (here on PATH, as ``cargo
install`` puts them); used from inside a checkout, it finds that checkout; and it says where it
looked when it finds none."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO, bin_dir, processes_mentioning, shm_leftovers

pytest.importorskip("pettingzoo")

BINARIES = ("formation", "formation-sim", "formation-agent", "formation-critic")


@pytest.fixture
def installed(tmp_path):
    """The package copied into a site directory of its own (no checkout around it), an empty
    working directory, and an environment without FORMATION_REPO or FORMATION_BIN_DIR."""
    site = tmp_path / "site"
    shutil.copytree(REPO / "python" / "formation_swarm", site / "formation_swarm",
                    ignore=shutil.ignore_patterns("__pycache__"))
    work = tmp_path / "work"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("FORMATION_REPO", "FORMATION_BIN_DIR", "PYTHONPATH")}
    # The test's own dependencies (iceoryx2, pettingzoo, ...) wherever pytest found them,
    # but not this checkout's python/ directory.
    paths = [str(site)] + [p for p in sys.path if p and Path(p).resolve() != (REPO / "python").resolve()]
    env["PYTHONPATH"] = os.pathsep.join(paths)
    return site, work, env


def run_python(code, work, env, timeout=180):
    return subprocess.run([sys.executable, "-c", code], cwd=str(work), env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_installed_package_finds_the_binaries_on_path(installed, tmp_path):
    site, work, env = installed
    # `cargo install` emulated: the built binaries in one directory on PATH.
    cargo_bin = tmp_path / "cargo-bin"
    cargo_bin.mkdir()
    for name in BINARIES:
        (cargo_bin / name).symlink_to(bin_dir() / name)
    env["PATH"] = f"{cargo_bin}{os.pathsep}{env.get('PATH', '')}"
    code = (
        "import formation_swarm as fs, formation_swarm.env as fe\n"
        f"assert fe.__file__.startswith({str(site)!r}), fe.__file__\n"
        f"env = fs.FormationEnv(n=3, seed=1, run_dir={str(tmp_path / 'runs')!r})\n"
        "print(env.launcher.found, flush=True)\n"
        "obs, _ = env.reset()\n"
        "for _ in range(3):\n"
        "    obs, rewards, *_ = env.step({a: [0.5, 0.0] for a in env.agents})\n"
        "print(env.run.run_id, env.world().tick, flush=True)\n"
        "env.close()\n"
    )
    done = run_python(code, work, env)
    assert done.returncode == 0, done.stdout + done.stderr
    found, run_line = done.stdout.splitlines()[:2]
    assert found == f"PATH, {cargo_bin}"
    run_id, tick = run_line.split()
    assert int(tick) == 3
    assert not shm_leftovers(run_id) and not processes_mentioning(run_id)
    assert done.stderr == ""


def test_installed_package_finds_the_checkout_around_the_current_directory(installed, tmp_path):
    """`pip install ./python`, then FormationEnv(n=3) from a directory inside a checkout, with no
    FORMATION_REPO, FORMATION_BIN_DIR or formation on PATH: the env runs that checkout's
    scripts/run_swarm.sh. The checkout here is made for the test: the real script, the package,
    and its target/release holding the tests' binaries; `cargo` on PATH is a stand-in that
    succeeds, so the script's release build is a no-op."""
    site, work, env = installed
    checkout = tmp_path / "checkout"
    (checkout / "scripts").mkdir(parents=True)
    shutil.copy2(REPO / "scripts" / "run_swarm.sh", checkout / "scripts" / "run_swarm.sh")
    shutil.copytree(site / "formation_swarm", checkout / "python" / "formation_swarm")
    release = checkout / "target" / "release"
    release.mkdir(parents=True)
    for name in BINARIES:
        (release / name).symlink_to(bin_dir() / name)
    tools = tmp_path / "tools"
    tools.mkdir()
    (tools / "cargo").write_text("#!/bin/sh\nexit 0\n")
    (tools / "cargo").chmod(0o755)
    env["PATH"] = f"{tools}{os.pathsep}{os.path.dirname(shutil.which('true'))}"
    env.pop("CARGO_TARGET_DIR", None)
    inside = checkout / "docs" / "notes"  # two levels below the checkout's top
    inside.mkdir(parents=True)
    code = (
        "import formation_swarm as fs, formation_swarm.env as fe\n"
        f"assert fe.__file__.startswith({str(site)!r}), fe.__file__\n"
        f"env = fs.FormationEnv(n=3, seed=2, run_dir={str(tmp_path / 'runs')!r})\n"
        "print(env.launcher.found, flush=True)\n"
        "obs, _ = env.reset()\n"
        "for _ in range(3):\n"
        "    obs, rewards, *_ = env.step({a: [0.5, 0.0] for a in env.agents})\n"
        "print(env.run.run_id, env.world().tick, flush=True)\n"
        "env.close()\n"
    )
    done = run_python(code, inside, env)
    assert done.returncode == 0, done.stdout + done.stderr
    found, run_line = done.stdout.splitlines()[:2]
    assert found == f"the checkout holding the current directory, {checkout}"
    run_id, tick = run_line.split()
    assert int(tick) == 3
    assert not shm_leftovers(run_id) and not processes_mentioning(run_id)
    assert done.stderr == ""


def test_no_binaries_anywhere_names_every_place_tried(installed, tmp_path):
    site, work, env = installed
    lone = tmp_path / "lone-bin"
    lone.mkdir()
    (lone / "formation").symlink_to(bin_dir() / "formation")  # a launcher without its members
    env["PATH"] = f"{lone}{os.pathsep}{os.path.dirname(shutil.which('true'))}"
    code = (
        "import formation_swarm as fs\n"
        "try:\n"
        "    fs.FormationEnv(n=3)\n"
        "except fs.FormationError as err:\n"
        "    print(err)\n"
    )
    done = run_python(code, work, env, timeout=60)
    assert done.returncode == 0, done.stderr
    message = done.stdout
    places = ("repo=", "FORMATION_REPO", "FORMATION_BIN_DIR",
              f"the checkout the package sits in ({site.parent} has no scripts/run_swarm.sh)",
              f"PATH (formation in {lone}, but not formation-sim, formation-agent, formation-critic",
              f"the checkout holding the current directory (neither {work} nor a directory above it",
              "or run from inside a checkout")
    for place in places:
        assert place in message, (place, message)
    assert "cargo install" in message
    # An explicit place that lacks the binaries is named as such, not passed over.
    env["FORMATION_BIN_DIR"] = str(lone)
    done = run_python(code, work, env, timeout=60)
    assert f"FORMATION_BIN_DIR {lone} lacks formation-sim" in done.stdout, done.stdout + done.stderr
