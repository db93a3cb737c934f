"""The set-up files a new user runs: compose file, CI script, install script."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

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


def test_install_script_is_a_no_op_when_everything_is_there() -> None:
    # This machine already has the packages (the test suite renders with them).
    r = subprocess.run(
        ["sh", str(ROOT / "scripts" / "install-system-deps.sh")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and r.stdout == "", r.stdout + r.stderr
