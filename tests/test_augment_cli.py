"""The augmentation commands of the real binary: a preview grid from a real dm_control frame, and the
benchmark's machine-readable output (its speed is measured in bench/, never asserted here)."""

import json
import struct
import subprocess
import zlib

from radserve.server import find_binary


def png_rows(path):
    """Width, height and the decoded RGB rows of an 8-bit RGB PNG (filter types as written)."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    offset, idat, header = 8, b"", None
    while offset < len(data):
        (length,) = struct.unpack(">I", data[offset : offset + 4])
        kind = data[offset + 4 : offset + 8]
        body = data[offset + 8 : offset + 8 + length]
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        offset += 12 + length
    width, height, depth, colour = header[:4]
    assert (depth, colour) == (8, 2), "8-bit RGB"
    raw = zlib.decompress(idat)
    stride = width * 3
    rows, previous = [], bytearray(stride)
    for y in range(height):
        kind = raw[y * (stride + 1)]
        line = bytearray(raw[y * (stride + 1) + 1 : (y + 1) * (stride + 1)])
        for x in range(stride):
            left = line[x - 3] if x >= 3 else 0
            up = previous[x]
            up_left = previous[x - 3] if x >= 3 else 0
            if kind == 1:
                line[x] = (line[x] + left) & 255
            elif kind == 2:
                line[x] = (line[x] + up) & 255
            elif kind == 3:
                line[x] = (line[x] + (left + up) // 2) & 255
            elif kind == 4:
                p = left + up - up_left
                pa, pb, pc = abs(p - left), abs(p - up), abs(p - up_left)
                predictor = left if pa <= pb and pa <= pc else up if pb <= pc else up_left
                line[x] = (line[x] + predictor) & 255
        rows.append(bytes(line))
        previous = line
    return width, height, rows


def test_preview_writes_a_grid_of_every_augmentation(tmp_path):
    out = tmp_path / "grid.png"
    result = subprocess.run(
        [find_binary(), "augment-preview", "--env", "dmc/cartpole-swingup", "--columns", "3", "--out", str(out)],
        capture_output=True, text=True, timeout=120, check=True,
    )
    rows = [line for line in result.stdout.splitlines() if line.startswith("row")]
    assert len(rows) == 15 and "crop(84)" in rows[1] and "color_jitter" in rows[10] and "shift(5)" in rows[13]
    width, height, pixels = png_rows(out)
    tile, gutter = 108, 4
    assert (width, height) == (3 * (tile + gutter) + gutter, 15 * (tile + gutter) + gutter)
    # The grayscale row (row 4) is gray in every tile; the original row (row 0) is not.
    def tile_pixels(row, column):
        top, left = gutter + row * (tile + gutter) + 4, gutter + column * (tile + gutter) + 4
        return [pixels[y][3 * x : 3 * x + 3] for y in range(top, top + 100) for x in range(left, left + 100)]
    assert all(p[0] == p[1] == p[2] for column in range(3) for p in tile_pixels(4, column))
    assert any(p[0] != p[2] for p in tile_pixels(0, 0))


def test_preview_refuses_a_state_environment(tmp_path):
    result = subprocess.run(
        [find_binary(), "augment-preview", "--env", "gym/CartPole-v1", "--out", str(tmp_path / "x.png")],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode != 0
    assert "does not observe images" in result.stderr


def test_bench_reports_every_case_with_its_shapes():
    result = subprocess.run(
        [find_binary(), "augment-bench", "--json", "--batch", "4", "--repeats", "1"],
        capture_output=True, text=True, timeout=120, check=True,
    )
    cases = {row["pipeline"]: row for row in map(json.loads, result.stdout.splitlines())}
    assert len(cases) == 14
    assert cases["crop(84)"]["input"] == [9, 100, 100] and cases["crop(84)"]["output"] == [9, 84, 84]
    assert cases["translate(108)"]["output_bytes"] == 4 * 9 * 108 * 108
    assert all(row["seconds"] > 0 and row["copy_seconds"] > 0 for row in cases.values())
