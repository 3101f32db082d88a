"""`bruce-import-data`: another simulator's trajectory (CSV or .npz, docs/byo_data.md) as our dataset `.npz`.

    bruce-import-data IN.csv|IN.npz --out OUT.npz [--config PATH] [--resample] [--ignore-extra] [--source-name TEXT]

Joints are mapped to the config's order by name, units converted to SI, and the file checked against the config
(rate, joint limits, plausible velocities and torques). A rate other than the config's loop rate is refused unless
--resample is given. OUT is what `bruce-collect` writes: `bruce-train --data OUT.npz` trains on it.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from bruce_hw.config import DEFAULT_CONFIG, ConfigError, load_config
from training.dataset import DatasetError, save_dataset
from training.external_data import convert, read_external


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bruce-import-data", description=__doc__.split("\n\n")[0],
                                epilog="The formats, the checks and the resampling rule: docs/byo_data.md")
    p.add_argument("source", type=Path, metavar="IN", help="the trajectory: a .csv or an external .npz")
    p.add_argument("--out", type=Path, required=True, metavar="OUT.npz", help="the dataset to write")
    p.add_argument("--config", default=DEFAULT_CONFIG, help="robot config YAML (default: %(default)s)")
    p.add_argument("--resample", action="store_true",
                   help="resample a file at another rate to rates.loop_hz (otherwise it is refused)")
    p.add_argument("--ignore-extra", action="store_true", help="drop the file's joints that the config lacks")
    p.add_argument("--source-name", metavar="TEXT", help="where the data came from, kept in the metadata "
                   "(e.g. 'Isaac Lab 2.1, rough terrain, seed 3')")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    command = shlex.join(["bruce-import-data", *(sys.argv[1:] if argv is None else argv)])
    try:
        config = load_config(args.config)
        dataset, conversion = convert(read_external(args.source), config, resample=args.resample,
                                      ignore_extra=args.ignore_extra, source_name=args.source_name, command=command)
        path = save_dataset(args.out, dataset)
    except (ConfigError, DatasetError) as exc:
        print(f"bruce-import-data: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the output cannot be written (a folder in its place, no permission)
        print(f"bruce-import-data: error: {args.out}: cannot write ({exc.strerror or exc})", file=sys.stderr)
        return 2
    print(f"bruce-import-data: wrote {path}: {conversion.describe()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
