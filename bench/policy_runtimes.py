"""Which runtime the server's actors use: the RAD actor (4 convs x 32 on 9x84x84, fc 50, LayerNorm,
MLP 1024 x 2; tests/policies.py) timed under tract (pure Rust) and ONNX Runtime (the onnxruntime
wheel's library through the `ort` crate, as the server runs it), in one process, same inputs,
batch = the session's envs. Builds bench/policy_runtimes (its own Cargo workspace: tract-onnx takes
~10 minutes to build on two cores), prints the table and writes bench/results/policy_runtimes.json
(docs/performance.md renders it).

    python bench/policy_runtimes.py [--batches 1,8,16] [--seconds 2] [--rounds 3]
"""

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
import record

policies = record.tests_helper("policies")

CRATE = ROOT / "bench" / "policy_runtimes"


def onnxruntime_library() -> Path:
    import onnxruntime

    found = sorted((Path(onnxruntime.__file__).parent / "capi").glob("libonnxruntime.so*"))
    if not found:
        sys.exit("no libonnxruntime.so in the onnxruntime wheel")
    return found[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batches", default="1,8,16")
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    subprocess.run(["cargo", "build", "--release", "--quiet", "--manifest-path", str(CRATE / "Cargo.toml")], check=True)
    binary = CRATE / "target" / "release" / "policy-runtimes"
    with tempfile.TemporaryDirectory() as scratch:
        model = Path(scratch) / "rad_actor.onnx"
        model.write_bytes(policies.rad_actor())
        output = subprocess.run([str(binary), str(model), str(onnxruntime_library()), "--batches", args.batches,
                                 "--seconds", str(args.seconds), "--rounds", str(args.rounds)],
                                check=True, capture_output=True, text=True).stdout
    results = [json.loads(line) for line in output.splitlines() if line.startswith("{")]
    by = {(r["runtime"], r["threads"], r["batch"]): r for r in results}
    rows = []
    for batch in sorted({r["batch"] for r in results}):
        tract, ort1, ort2 = by[("tract", 1, batch)], by[("onnxruntime", 1, batch)], by[("onnxruntime", 2, batch)]
        per_env = lambda r: record.cell(r["ms_per_call"] / batch, r["low"] / batch, r["high"] / batch, 2)  # noqa: E731
        rows.append([batch, per_env(tract), per_env(ort1), per_env(ort2),
                     record.cell(tract["ms_per_call"] / ort1["ms_per_call"], digits=2, suffix="x")])
    table = {
        "id": "policy_runtimes",
        "columns": ["batch (envs)", "tract, 1 thread (ms per env step)", "ONNX Runtime, 1 thread", "ONNX Runtime, 2 threads",
                    "tract / ONNX Runtime (1 thread)"],
        "rows": rows,
        "note": "RAD actor (tests/policies.py rad_actor), uint8 input [batch, 9, 84, 84]; median of the rounds (range)",
    }
    for row in rows:
        print(record.plain(row))
    record.write("policy_runtimes", [table], settings=vars(args))


if __name__ == "__main__":
    main()
