"""python -m warp_hcell.clean DB.h5 [--out CLEAN.h5]

The cleaning step of the learning database: marks pathological samples in ``valid`` and
records what it removed. Nothing is deleted: a removed sample stays in the file with
``valid = False``, so the step can be audited and undone.

A sample is removed for each of these reasons (``REASONS``; a sample may have several):

- ``alpha_range``: alpha before or after the probe outside [30, 90] deg (the H-cell is no
  longer admissible: grains 2-6 or 1-4 interpenetrate);
- ``mechanism``: before or after the probe no contact is closed; the cell is a stress-free
  mechanism whose alpha is not fixed by equilibrium (for the DEM it is wherever the free
  grains stopped), so the output carries no learnable information;
- ``unconverged``: the backend did not reach quasi-static equilibrium (``converged`` False);
- ``non_finite``: a non-finite value in ``inputs`` or ``outputs``.

Root attrs written: ``cleaned`` (bool), ``n_valid``, ``removed_<reason>`` (count per
reason), ``n_removed`` (samples with at least one reason) and ``cleaning`` (JSON: rules
and counts). Without cleaning (``not_cleaned``) every sample is valid and ``cleaned`` is
False. The command rewrites the file atomically (temporary file, then rename): an
interrupted run leaves the original intact.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from warp_hcell import database
from warp_hcell.parameters import ALPHA_MAX_DEG, ALPHA_MIN_DEG

ALPHA_TOLERANCE_DEG = 1e-9
"""Rounding allowance of the alpha range [deg]: a cell built at alpha0 = 30 deg reads
29.999999999999996 deg."""

REASONS = {
    "alpha_range": f"alpha before or after the probe outside [{ALPHA_MIN_DEG:g}, {ALPHA_MAX_DEG:g}] deg",
    "mechanism": "no closed contact before or after the probe (stress-free mechanism)",
    "unconverged": "the backend did not reach quasi-static equilibrium",
    "non_finite": "non-finite value in inputs or outputs",
}
"""Cleaning reasons and their rules."""


def alpha_in_range(alpha_deg: np.ndarray) -> np.ndarray:
    """True where alpha [deg] lies in [30, 90] deg, to within ``ALPHA_TOLERANCE_DEG``."""
    return (alpha_deg >= ALPHA_MIN_DEG - ALPHA_TOLERANCE_DEG) & (alpha_deg <= ALPHA_MAX_DEG + ALPHA_TOLERANCE_DEG)


def pathological(samples: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per-reason masks of the samples to remove.

    Args:
        samples: per-sample datasets (at least ``inputs``, ``outputs``, ``pre_state``,
            ``post_state``, ``converged``).

    Returns:
        ``REASONS`` key -> bool array (n_samples,), True = remove.
    """
    col = {name: i for i, name in enumerate(database.STATE_FEATURES)}
    pre, post = samples["pre_state"], samples["post_state"]

    def out_of_range(table: np.ndarray) -> np.ndarray:
        return ~alpha_in_range(table[:, col["alpha_deg"]])

    def open_cell(table: np.ndarray) -> np.ndarray:
        return ~((table[:, col["closed1"]] > 0.0) | (table[:, col["closed2"]] > 0.0))

    return {
        "alpha_range": out_of_range(pre) | out_of_range(post),
        "mechanism": open_cell(pre) | open_cell(post),
        "unconverged": ~np.asarray(samples["converged"], dtype=bool),
        "non_finite": ~(np.isfinite(samples["inputs"]).all(axis=1) & np.isfinite(samples["outputs"]).all(axis=1)),
    }


def _attrs(valid: np.ndarray, masks: Mapping[str, np.ndarray] | None) -> dict[str, Any]:
    removed = {reason: int(np.count_nonzero(mask)) for reason, mask in (masks or {}).items()}
    attrs: dict[str, Any] = {"cleaned": masks is not None, "n_valid": int(np.count_nonzero(valid)),
                             "n_removed": int(valid.size - np.count_nonzero(valid))}
    attrs.update({f"removed_{reason}": count for reason, count in removed.items()})
    attrs["cleaning"] = json.dumps({"applied": masks is not None, "rules": REASONS if masks is not None else {},
                                    "removed": removed}, sort_keys=True)
    return attrs


def clean_samples(samples: Mapping[str, np.ndarray]) -> tuple[np.ndarray, dict[str, Any]]:
    """Apply the cleaning rules.

    Returns:
        (valid (n_samples,) bool, root attrs describing what was removed).
    """
    masks = pathological(samples)
    valid = ~np.logical_or.reduce(list(masks.values()))
    return valid, _attrs(valid, masks)


def not_cleaned(samples: Mapping[str, np.ndarray]) -> tuple[np.ndarray, dict[str, Any]]:
    """Every sample valid, and the attrs saying that no cleaning was applied."""
    valid = np.ones(np.shape(samples["converged"])[0], dtype=bool)
    return valid, _attrs(valid, None)


def clean_file(path: Path, out: Path) -> dict[str, Any]:
    """Clean database ``path`` and write it to ``out`` (may equal ``path``) atomically.

    Returns:
        The cleaning attrs written.
    """
    samples, states, attrs = database.read_database(path)
    samples["valid"], cleaning_attrs = clean_samples(samples)
    attrs.update(cleaning_attrs)
    database.write_database(Path(out), samples, states, attrs)
    return cleaning_attrs


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: clean a database file (see the module docstring)."""
    parser = argparse.ArgumentParser(
        prog="python -m warp_hcell.clean", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Mark pathological samples of a learning database in `valid` and record the counts per "
                    "reason (alpha range, mechanism, unconverged, non-finite) as root attrs.")
    parser.add_argument("database", type=Path, help="database file written by warp_hcell.generate")
    parser.add_argument("--out", type=Path, default=None, help="write the cleaned file here; unset: clean in place")
    parser.error = lambda message: parser.exit(2, f"{parser.prog}: error: {message}\n")  # one line, exit 2
    args = parser.parse_args(argv)
    out = args.out or args.database
    if not args.database.is_file():
        parser.error(f"{args.database}: no such database file")
    if args.out is not None and args.out.exists():
        parser.error(f"{args.out} exists; remove it or clean in place")
    try:
        summary = clean_file(args.database, out)
    except (OSError, ValueError) as exc:
        parser.error(" ".join(str(exc).split()))
    except KeyError as exc:
        parser.error(f"{args.database}: not a complete learning database ({exc.args[0] if exc.args else exc})")
    print(f"{out}: {summary['n_valid']} valid, {summary['n_removed']} removed "
          + ", ".join(f"{reason} {summary[f'removed_{reason}']}" for reason in REASONS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
