#!/usr/bin/env python3
"""Reference corners for the parity test, from the AprilTag library itself.

Reads every frame_*.pgm in the parity fixture folder (written by
`MARKHOLD_PARITY_REFRESH=1 cargo test --release -p markhold-vision --test parity`),
runs the AprilTag 3 detector (PyPI package apriltag-python) on it and writes
reference.csv: file, id, then the four corners as the library reports them
(lb, rb, rt, lt; (0, 0) is the outer corner of the top-left pixel).

Usage: pip install apriltag-python numpy; python3 apriltag_reference.py [folder]
"""
import pathlib
import sys

import numpy as np
from apriltag import apriltag


def read_pgm(path):
    data = path.read_bytes()
    # Binary PGM: "P5\n<w> <h>\n<max>\n" then the pixels.
    fields = data.split(maxsplit=4)
    assert fields[0] == b"P5", path
    w, h, maxval = int(fields[1]), int(fields[2]), int(fields[3])
    assert maxval == 255, path
    pixels = fields[4]
    return np.frombuffer(pixels[: w * h], dtype=np.uint8).reshape(h, w)


def main():
    folder = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else
                          pathlib.Path(__file__).resolve().parent.parent / "fixtures" / "parity")
    detector = apriltag("tag36h11")  # decimate 1, no blur: full-resolution quads
    rows = ["file,id,lb_x,lb_y,rb_x,rb_y,rt_x,rt_y,lt_x,lt_y"]
    for pgm in sorted(folder.glob("frame_*.pgm")):
        for d in detector.detect(read_pgm(pgm)):
            c = d["lb-rb-rt-lt"]
            coords = ",".join(f"{v:.6f}" for p in c for v in p)
            rows.append(f"{pgm.with_suffix('.png').name},{d['id']},{coords}")
    (folder / "reference.csv").write_text("\n".join(rows) + "\n")
    print(f"{len(rows) - 1} detections written to {folder / 'reference.csv'}")


if __name__ == "__main__":
    main()
