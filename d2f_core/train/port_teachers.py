"""``d2f-train port-teachers SRC OUT``: convert every shipped scene teacher at once.

Runs the three converters (:mod:`.port_deeplab` for the ADE20K and VOC DeepLab files,
:mod:`.port_u2net`, :mod:`.port_fastdepth`) on the original files in ``SRC`` (for example
``../shared/datasets/teachers``) and writes the torch weights into ``OUT`` (``assets/weights``
for the shipped ones). Reading the TFLite and ONNX files needs the ``teach`` extra
(``pip install -e ".[teach]"``); the converted weights need only torch.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

__all__ = ["convert_all", "main"]


def convert_all(src: Path, out: Path) -> list[Path]:
    """Convert every teacher in ``src`` into ``out``; the files written, in order."""
    from . import port_deeplab, port_fastdepth, port_u2net

    src, out = Path(src), Path(out)
    if not src.is_dir():
        raise ValueError(f"{src}: not a folder of teacher files")
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for module in (port_deeplab, port_u2net, port_fastdepth):
        written += module.convert(src, out)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="d2f-train port-teachers",
        description="convert the scene teachers (DeepLab ADE20K and VOC, U^2-Net-p, "
        "FastDepth) from their original files into the torch weights the scene source loads",
    )
    parser.add_argument("src", type=Path, help="folder of the original files")
    parser.add_argument("out", type=Path, help="folder for teacher_*.pt (e.g. assets/weights)")
    args = parser.parse_args(argv)
    try:
        for path in convert_all(args.src, args.out):
            print(f"wrote {path}")
    except (OSError, ValueError, ImportError) as exc:
        print(f"d2f-train port-teachers: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
