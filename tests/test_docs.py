"""The generated parts of the docs are current, and the README stays a manual: every benchmark table
shown in the README and docs/ is the rendering of its results file (bench/results/), the
configuration reference is what the binary prints, and the README keeps to its length."""

import subprocess
import sys
from pathlib import Path

from radserve.server import find_binary

ROOT = Path(__file__).resolve().parents[1]


def test_tables_and_the_configuration_reference_are_rendered_from_their_sources():
    checked = subprocess.run([sys.executable, str(ROOT / "scripts" / "docs_tables.py"), "--check", "--binary", find_binary()],
                             capture_output=True, text=True)
    assert checked.returncode == 0, checked.stderr + checked.stdout


def test_a_stale_table_is_found(tmp_path):
    """The check itself fails on a page whose table differs from its results file."""
    from _procs import script

    docs_tables = script("docs_tables")

    rendered = docs_tables.tables()
    assert rendered, "bench/results/ holds no table"
    some_id = sorted(rendered)[0]
    page = f"intro\n<!-- BEGIN table:{some_id} -->\n| stale | 1 |\n<!-- END table:{some_id} -->\n"
    fresh = docs_tables.render_page(page, rendered, find_binary(), "page.md")
    assert fresh != page and rendered[some_id] in fresh
    assert docs_tables.render_page(fresh, rendered, find_binary(), "page.md") == fresh


def test_the_readme_is_a_manual_of_at_most_250_lines():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 250, f"README.md has {len(lines)} lines: move detail into docs/"


def _missing_from_architecture(page: str) -> "list[str]":
    """The crates, modules and long files (over 600 lines) that docs/architecture.md does not name."""
    missing = []
    for manifest in sorted((ROOT / "server").glob("*/Cargo.toml")):
        crate = manifest.parent
        if f"{crate.name}/" not in page:
            missing.append(f"crate {crate.name}")
        missing += [f"module {path.relative_to(ROOT)}" for path in sorted((crate / "src").rglob("*.rs"))
                    if path.name not in ("lib.rs", "mod.rs") and path.name not in page]
    for package in (ROOT / "client-py" / "radserve", ROOT / "server" / "sim" / "python" / "radserve_worker"):
        missing += [f"module {path.relative_to(ROOT)}" for path in sorted(package.glob("*.py")) if path.name not in page]
    tracked = subprocess.run(["git", "ls-files", "*.rs", "*.py"], cwd=ROOT, capture_output=True, text=True, check=True)
    for name in tracked.stdout.split():
        path = ROOT / name
        if path.is_file() and len(path.read_text(errors="replace").splitlines()) > 600 and name.split("/")[-1] not in page:
            missing.append(f"long file {name}")
    return missing


def test_the_architecture_page_names_every_crate_module_and_long_file():
    page = (ROOT / "docs" / "architecture.md").read_text()
    assert _missing_from_architecture(page) == []
    # The check sees a module the page stops naming.
    assert _missing_from_architecture(page.replace("rate_limiter.rs", "")) == ["module server/replay/src/rate_limiter.rs"]
