"""Record the fidelity test's golden traces (``tests/data/golden/``) from this checkout.

Run it only when a change of the model's behaviour is intended, and say so in the commit:
the fidelity test (``tests/test_fidelity.py``) holds every optimisation to these traces.
``python tools/record_golden.py [--out DIR]``."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tests import fidelity


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=fidelity.GOLDEN)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as state:
        for name, scenario in fidelity.scenarios(Path(state)).items():
            frames = scenario()
            (args.out / f"{name}.trace.gz").write_bytes(fidelity.dump(frames))
            print(f"{name}: {len(frames)} frames")


if __name__ == "__main__":
    main()
