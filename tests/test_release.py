"""What a release is made of, checked against the real binary and server: one version everywhere (the
Cargo workspace's), the packages' metadata agreeing with the locks, and the files a release ships."""

import re
import subprocess
import tomllib
from pathlib import Path

import radserve
from radserve.server import find_binary

ROOT = Path(__file__).resolve().parents[1]


def cargo_version() -> str:
    return tomllib.loads((ROOT / "Cargo.toml").read_text())["workspace"]["package"]["version"]


def test_every_part_reports_the_workspace_version(client):
    version = cargo_version()
    assert re.fullmatch(r"\d+\.\d+\.\d+", version), version
    assert radserve.__version__ == version, "client-py/radserve/_version.py must say the Cargo workspace's version"
    printed = subprocess.run([find_binary(), "--version"], capture_output=True, text=True, check=True).stdout
    assert printed.strip() == f"radserve {version}"
    (info,) = client.server_info()
    assert (info.version, info.api) == (version, "radserve.v1")
    # The client's `server` extra installs the server wheel of the same release.
    extras = tomllib.loads((ROOT / "client-py" / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert extras["server"] == [f"radserve-server=={version}"]


def pinned(lines) -> "dict[str, str]":
    """name -> requirement, for requirement lines (comments and blanks left out)."""
    found = {}
    for line in lines:
        requirement = line.split("#", 1)[0].strip()
        if requirement:
            found[re.split(r"[\[=<>!~ ]", requirement, 1)[0].lower()] = requirement.replace(" ", "")
    return found


def test_the_server_wheel_declares_the_simulators_at_the_locked_pins():
    declared = pinned(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"])
    wanted = pinned((ROOT / "requirements.in").read_text().splitlines())
    for name, requirement in declared.items():
        assert wanted.get(name) == requirement, f"{requirement} in the server wheel, {wanted.get(name)} in requirements.in"
    # Every simulator the workers import is declared.
    assert {"dm-control", "mujoco", "gymnasium", "procgen-mirror", "numpy"} <= declared.keys()


def test_a_release_ships_its_license_changelog_and_security_policy():
    license_text = (ROOT / "LICENSE").read_text()
    assert "Apache License" in license_text and "END OF TERMS AND CONDITIONS" in license_text
    # The client's sdist and wheel carry the same text (setuptools reads license files inside the project).
    assert (ROOT / "client-py" / "LICENSE").read_text() == license_text
    assert f"## [{cargo_version()}]" in (ROOT / "CHANGELOG.md").read_text()
    assert "Reporting a vulnerability" in (ROOT / "SECURITY.md").read_text()
