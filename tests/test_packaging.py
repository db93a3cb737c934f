"""The set-up files a new user runs: compose file, CI script, install script."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent


def test_compose_file_runs_the_demo_from_the_dockerfile() -> None:
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    demo = compose["services"]["demo"]
    assert (ROOT / demo["build"] / "Dockerfile").is_file()
    assert demo["command"][0] == "demo"
    dockerfile = (ROOT / "Dockerfile").read_text()
    for package in ("facewire", "models", "sender", "receiver", "protocol"):
        assert f"COPY {package} {package}" in dockerfile
    assert 'ENTRYPOINT ["facewire"]' in dockerfile


def test_scripts_are_executable_and_valid_shell() -> None:
    for script in (ROOT / ".ci" / "run", ROOT / "scripts" / "install-system-deps.sh"):
        assert os.access(script, os.X_OK), script
        shell = "bash" if script.name == "run" else "sh"
        subprocess.run([shell, "-n", str(script)], check=True)


@pytest.mark.parametrize("options", [[], ["--test"]], ids=["run", "test"])
def test_install_script_is_a_no_op_when_everything_is_there(options: list[str]) -> None:
    # This machine already has the packages (the test suite renders with them, and `make
    # test` ran the script with --test).
    r = subprocess.run(
        ["sh", str(ROOT / "scripts" / "install-system-deps.sh"), *options],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and r.stdout == "", r.stdout + r.stderr


def _compose_config() -> dict:
    """docker-compose.yml as Debian's docker-compose (1.29) reads it: its ``config`` command
    validates the file against the Compose specification's schema and prints it resolved."""
    tool = shutil.which("docker-compose")
    if tool is None:
        pytest.skip("docker-compose is not installed (scripts/install-system-deps.sh --test)")
    r = subprocess.run(
        [tool, "-f", str(ROOT / "docker-compose.yml"), "config"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    return yaml.safe_load(r.stdout)


def test_compose_file_is_valid_and_runs_a_call_between_two_services() -> None:
    from facewire.cli import build_parser

    services = _compose_config()["services"]
    receiver, sender = services["receiver"], services["sender"]
    # Their own network, the live view's port published on the host.
    assert receiver["networks"] == sender["networks"] == {"call": None}
    assert {"published": 8080, "target": 8080} in receiver["ports"]
    parser = build_parser()
    received = parser.parse_args(receiver["command"])
    sent = parser.parse_args(sender["command"])
    assert received.command == "receive" and sent.command == "send"
    # The sender plays the bundled clip (no --input, no camera) and connects to the receiver
    # by its service name, at the port the receiver binds; keys each way.
    assert sent.input is None and sent.camera is None and sent.loop
    port = received.bind.rsplit(":", 1)[1]
    assert received.bind == f"tcp://*:{port}" and sent.connect == f"tcp://receiver:{port}"
    assert Path(received.key).stem == Path(sent.peer[0]).stem == "receiver"
    assert Path(sent.key).stem == Path(received.peer[0]).stem == "sender"
    # The receiver serves its live view on the published port, on every interface.
    assert received.view == "0.0.0.0:8080"
    assert services["keys"]["volumes"][0].startswith("keys:/keys")
    # The image renders through EGL.
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert "ENV PYOPENGL_PLATFORM=egl" in dockerfile and "libegl-mesa0" in dockerfile


def test_compose_validation_catches_a_broken_file(tmp_path: Path) -> None:
    tool = shutil.which("docker-compose")
    if tool is None:
        pytest.skip("docker-compose is not installed (scripts/install-system-deps.sh --test)")
    text = (ROOT / "docker-compose.yml").read_text().replace("ports:", "portz:")
    (tmp_path / "docker-compose.yml").write_text(text)
    r = subprocess.run(
        [tool, "-f", str(tmp_path / "docker-compose.yml"), "config", "-q"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode != 0 and "portz" in r.stderr


def test_secret_keys_stay_out_of_git() -> None:
    # `facewire keys --out keys`, as the docs have it, writes into the checkout.
    if not (ROOT / ".git").exists() or shutil.which("git") is None:
        pytest.skip("not a git checkout")
    r = subprocess.run(
        ["git", "-C", str(ROOT), "check-ignore", "--no-index", "keys/sender.key_secret"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stdout + r.stderr


def test_the_wheel_is_one_package_that_runs_the_demo_and_the_build_warns_of_nothing(
    tmp_path: Path,
) -> None:
    """`make demo`'s editable install, and a wheel, built by the setuptools pyproject.toml
    asks for: no deprecation (project.license as a table) and no editable-install warning;
    the wheel holds facewire alone, and installed in a fresh venv it runs the demo."""
    project = tmp_path / "facewire"
    project.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, project)
    for package in ("facewire", "models", "sender", "receiver", "protocol"):
        shutil.copytree(
            ROOT / package, project / package, ignore=shutil.ignore_patterns("__pycache__")
        )
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    python = str(venv / "bin" / "python")
    requires = tomllib.loads((ROOT / "pyproject.toml").read_text())["build-system"]["requires"]
    pip = subprocess.run(
        [python, "-m", "pip", "install", "--quiet", *requires],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if pip.returncode != 0:
        pytest.skip(f"cannot install {requires}: {pip.stderr.strip().splitlines()[-1:]}")
    build = (
        "import sys\n"
        "from setuptools import build_meta\n"
        "print(build_meta.build_wheel(sys.argv[1]))\n"
        "print(build_meta.build_editable(sys.argv[1]))\n"
    )
    r = subprocess.run(
        [python, "-W", "always", "-c", build, str(tmp_path / "dist")],
        cwd=project,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert "editable" in r.stdout
    said = r.stdout + r.stderr
    assert "Warning" not in said and "!!" not in said, said
    # One import package: the parts install inside facewire, nothing else at the top.
    wheel = next((tmp_path / "dist").glob("facewire-*-py3-none-any.whl"))
    with zipfile.ZipFile(wheel) as archive:
        top = {name.split("/")[0] for name in archive.namelist()}
        assert "facewire/protocol/packets.py" in archive.namelist()
        assert "facewire/models/data/canonical_face_mesh.obj" in archive.namelist()
    assert top == {"facewire", wheel.name.split("-py3")[0] + ".dist-info"}, top
    pip = [python, "-m", "pip", "install", "--quiet", "--no-deps", str(wheel)]
    subprocess.run(pip, check=True, timeout=300)
    where = (
        "import importlib.util as u\n"
        "print([bool(u.find_spec(n)) for n in ('facewire.sender', 'facewire.receiver', "
        "'facewire.protocol', 'facewire.models', 'sender', 'receiver', 'protocol', 'models')])\n"
    )
    # Without PYTHONPATH: a checkout put on it (a worktree's tests) would be found instead.
    env = {**os.environ, "PYOPENGL_PLATFORM": "egl", "PYTHONPATH": ""}
    found = subprocess.run(
        [python, "-c", where], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60
    )
    assert found.stdout.strip() == str([True] * 4 + [False] * 4), found.stdout + found.stderr
    # The installed wheel runs the demo outside the checkout. Its dependencies come from this
    # environment's site-packages (a path entry after the venv's own, so the wheel's facewire
    # is the one imported), not from the network.
    ask = "import site; print(site.getsitepackages()[0])"
    site = Path(subprocess.check_output([python, "-c", ask], text=True).strip())
    deps = [p for p in sys.path if p.endswith("site-packages")]
    (site / "facewire-test-deps.pth").write_text("\n".join(deps) + "\n")
    demo = subprocess.run(
        [str(venv / "bin" / "facewire"), "demo", "--frames", "20", "--no-sound",
         "--stats", "demo.json"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert demo.returncode == 0, demo.stdout + demo.stderr
    stats = json.loads((tmp_path / "demo.json").read_text())
    assert stats["frames_out"] == 20 and (tmp_path / "demo-output.mp4").stat().st_size > 0
    where = [python, "-c", "import facewire.receiver.session as m; print(m.__file__)"]
    imported = subprocess.check_output(where, cwd=tmp_path, env=env, text=True).strip()
    assert Path(imported).is_relative_to(site), imported


def test_an_image_build_sends_what_the_dockerfile_copies_and_no_more(tmp_path: Path) -> None:
    """The build context as Debian's docker-compose (docker-py) packs it, .dockerignore
    applied, of a checkout after `make demo` and a call: no .venv, keys, outputs or .git."""
    python = shutil.which("python3", path="/usr/bin")
    probe = [python or "python3", "-c", "import docker.utils.build"]
    if python is None or subprocess.run(probe, capture_output=True).returncode != 0:
        pytest.skip("no docker-py (Debian's docker-compose; scripts/install-system-deps.sh --test)")
    dockerfile = (ROOT / "Dockerfile").read_text()
    copied = [
        source
        for line in dockerfile.splitlines()
        if line.startswith("COPY ")
        for source in line.split()[1:-1]
    ]
    kept = [f"{c}/x.py" if (ROOT / c).is_dir() else c for c in copied]
    left_out = [
        ".venv/bin/python",
        ".venv/lib/python3.11/site-packages/cv2/cv2.so",
        "keys/alice.key_secret",
        "out/call.mp4",
        ".git/HEAD",
        "demo-output.mp4",
        "demo-stats.json",
        "facewire/__pycache__/cli.cpython-311.pyc",
        "facewire.egg-info/PKG-INFO",
    ]
    for name in [*kept, *left_out, "Dockerfile", ".dockerignore"]:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("x")
    shutil.copy(ROOT / ".dockerignore", tmp_path)
    context = (
        "import sys\n"
        "from docker.utils.build import exclude_paths\n"
        "lines = open(sys.argv[1] + '/.dockerignore').read().splitlines()\n"
        "patterns = [p.strip() for p in lines if p.strip() and not p.startswith('#')]\n"
        "print('\\n'.join(sorted(exclude_paths(sys.argv[1], patterns, 'Dockerfile'))))\n"
    )
    r = subprocess.run(
        [python, "-c", context, str(tmp_path)], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0, r.stderr
    sent = set(r.stdout.split())
    assert set(kept) <= sent, set(kept) - sent
    assert not sent & set(left_out), sent & set(left_out)


def test_make_demo_installs_what_running_needs_and_make_test_the_dev_tools(
    tmp_path: Path,
) -> None:
    if shutil.which("make") is None:
        pytest.skip("no make")
    for name in ("Makefile", "pyproject.toml", "scripts/install-system-deps.sh"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / name, tmp_path / name)

    def planned(target: str) -> list[str]:
        r = subprocess.run(
            ["make", "-n", target], cwd=tmp_path, capture_output=True, text=True, timeout=60
        )
        assert r.returncode == 0, r.stderr
        return [line for line in r.stdout.splitlines() if "pip install" in line]

    demo, test = planned("demo"), planned("test")
    assert not any("[dev]" in line for line in demo), demo
    # pip shows its progress while facewire's dependencies install: no minute of silence.
    assert any(" -e ." in line and "--quiet" not in line for line in demo), demo
    assert any("[dev]" in line for line in test), test
    dev = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert {"pytest", "mypy", "ruff"} <= {re.split(r"[<>=\[]", d)[0] for d in dev["dev"]}


def test_the_parts_are_imported_only_inside_facewire() -> None:
    # `import protocol` would load a second copy of a part beside facewire.protocol (its own
    # constants and classes), and break where another package has that name.
    short = re.compile(r"^\s*(from|import)\s+(sender|receiver|protocol|models)\b", re.M)
    found = []
    for folder in ("facewire", "sender", "receiver", "protocol", "models", "tests", "benchmarks",
                   "tools"):  # fmt: skip
        for path in (ROOT / folder).rglob("*.py"):
            found += [f"{path.relative_to(ROOT)}: {m.group(0).strip()}"
                      for m in short.finditer(path.read_text())]  # fmt: skip
    assert not found, found
