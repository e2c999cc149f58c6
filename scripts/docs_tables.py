"""Renders the generated parts of the README and docs/ (`make docs-tables`), or checks that they are
current (`--check`, run by tests/test_docs.py):

- every `<!-- BEGIN table:<id> -->` ... `<!-- END table:<id> -->` block becomes the table `<id>` of a
  results file in bench/results/ (bench/record.py writes them), with one line under it naming the
  command, the machine, the date and the commit it came from;
- the `<!-- BEGIN radserve config --markdown -->` block of docs/configuration.md becomes what the
  binary prints for `radserve config --markdown` (the configuration types' own documentation).

    .venv/bin/python scripts/docs_tables.py [--check] [--binary target/release/radserve]
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
TABLE_BLOCK = re.compile(r"(<!-- BEGIN table:(?P<id>[a-z0-9_]+) -->\n)(?P<body>.*?)(<!-- END table:(?P=id) -->)", re.S)
CONFIG_BLOCK = re.compile(r"(<!-- BEGIN radserve config --markdown -->\n)(?P<body>.*?)(<!-- END radserve config --markdown -->)", re.S)


def number(value: float, digits: int) -> str:
    return f"{value:,.{digits}f}"


def render_cell(cell) -> str:
    if isinstance(cell, str):
        return cell.replace("|", "\\|")  # a pipeline's `|` would end the column
    if isinstance(cell, (int, float)):
        return number(cell, 0 if isinstance(cell, int) else 2)
    digits, suffix = cell.get("digits", 0), cell.get("suffix", "")
    text = number(cell["value"], digits) + suffix
    if "low" in cell and "high" in cell:
        text += f" ({number(cell['low'], digits)}-{number(cell['high'], digits)})"
    return text


def render_table(table: dict, document: dict) -> str:
    columns = table["columns"]
    align = table.get("align") or ["l"] + ["r"] * (len(columns) - 1)
    rule = ["---:" if side == "r" else "---" for side in align]
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join(rule) + "|"]
    for row in table["rows"]:
        if len(row) != len(columns):
            raise ValueError(f"table {table['id']} of {document['bench']}: a row of {len(row)} cells under {len(columns)} columns")
        lines.append("| " + " | ".join(render_cell(cell) for cell in row) + " |")
    machine = document["machine"]
    source = (f"`{document['command']}` on {machine['cpu']} ({machine['cores']} cores, {machine['memory_gib']:g} GiB), "
              f"{document['date']}, commit {document['commit']}.")
    if table.get("note"):
        source += " " + table["note"]
    return "\n".join(lines) + "\n\n" + source + "\n"


def tables() -> "dict[str, str]":
    """Every table of every results file, rendered, by id."""
    rendered = {}
    for path in sorted(RESULTS.glob("*.json")):
        document = json.loads(path.read_text())
        for table in document["tables"]:
            if table["id"] in rendered:
                raise ValueError(f"table id {table['id']} appears twice (again in {path.name})")
            rendered[table["id"]] = render_table(table, document)
    return rendered


def config_markdown(binary: str) -> str:
    return subprocess.run([binary, "config", "--markdown"], capture_output=True, text=True, check=True).stdout


def render_page(text: str, rendered: "dict[str, str]", binary: str, page: str) -> str:
    def table(match: re.Match) -> str:
        if match["id"] not in rendered:
            raise KeyError(f"{page} asks for table:{match['id']}, which no file in bench/results/ has")
        return match.group(1) + rendered[match["id"]] + match.group(4)

    text = TABLE_BLOCK.sub(table, text)
    if CONFIG_BLOCK.search(text):
        text = CONFIG_BLOCK.sub(lambda match: match.group(1) + config_markdown(binary) + match.group(3), text)
    return text


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 naming each stale page")
    parser.add_argument("--binary", default=str(ROOT / "target" / "release" / "radserve"))
    args = parser.parse_args()
    rendered = tables()
    used, stale = set(), []
    for path in PAGES:
        text = path.read_text()
        used.update(match["id"] for match in TABLE_BLOCK.finditer(text))
        new = render_page(text, rendered, args.binary, path.name)
        if new != text:
            stale.append(path.relative_to(ROOT))
            if not args.check:
                path.write_text(new)
    unused = sorted(set(rendered) - used)
    if unused:
        print(f"docs_tables: results tables that no page shows: {', '.join(unused)}", file=sys.stderr)
    if args.check:
        for page in stale:
            print(f"docs_tables: {page} differs from its results files or the configuration: run `make docs-tables`",
                  file=sys.stderr)
        return 1 if stale or unused else 0
    for page in stale:
        print(f"docs_tables: rewrote {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
