"""Convert the Dobrany sand lab protocol (an Excel workbook) into the package's measured-curve CSVs.

Source: ``dataset/SoilModels-labProtocol-Sand.xlsx`` of the public repository
filippo-masi/ALERT-OlekZienkiewicz-ML (MIT licence, copyright 2025 Filippo Masi; see
``LICENSE-source.txt`` beside this script). Needs ``openpyxl`` (MIT), which the package itself
does not depend on: ``pip install openpyxl``.

Output, beside this script:

- ``cid_50kpa.csv``, ``cid_100kpa.csv``, ``cid_200kpa.csv``: the drained triaxial compression
  tests (sheets CID-REC-1..3) in the format of ``homogenization.calibration.data`` (test
  ``triaxial_drained``, ``p0`` = the radial effective stress [Pa]; columns eps1 [-], q [Pa],
  eps_v [-], compression and contraction positive). The sheets give eps_a and eps_v in percent
  with dilatancy negative, i.e. contraction already positive; q and sigma_r' in kPa.
  Rows at eps1 = 0 and rows whose eps1 does not increase are left out and counted.
- ``oed_loose.csv``: the oedometric loading-unloading of the loose specimen (sheet OED-REC-1):
  sigma_a [Pa], eps_a [-] (compression positive), in the order of the test.
- ``specimens.json``: each test's initial void ratio (at the start of shear), sheet, rows kept
  and rows left out, and the soil description of the NOTES and IDX AND GRAD sheets.

Usage: ``python convert_lab_protocol.py PATH/TO/SoilModels-labProtocol-Sand.xlsx``
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

KPA = 1.0e3
"""Pa per kPa."""
PERCENT = 1.0e-2
"""Fraction per percent."""
CID_SHEETS = {"CID-REC-1": "cid_50kpa.csv", "CID-REC-2": "cid_100kpa.csv", "CID-REC-3": "cid_200kpa.csv"}
"""Drained triaxial sheets -> output file."""
SOURCE = ("filippo-masi/ALERT-OlekZienkiewicz-ML, dataset/SoilModels-labProtocol-Sand.xlsx "
          "(MIT licence, copyright 2025 Filippo Masi)")


def _numeric_rows(sheet, first_row: int) -> list[tuple[float, ...]]:
    """Rows from ``first_row`` on whose leading cells are numbers (stops at the first blank row)."""
    rows = []
    for values in sheet.iter_rows(min_row=first_row, values_only=True):
        cells = [v for v in values if v is not None]
        if not cells:
            break
        rows.append(tuple(float(v) for v in cells))
    return rows


def convert_cid(sheet, out: Path) -> dict:
    """Write one drained triaxial sheet as a measured-curve CSV; returns its record."""
    void_ratio = float(sheet.cell(1, 2).value)
    rows = _numeric_rows(sheet, 3)
    sigma_r = {r[1] for r in rows}
    if len(sigma_r) != 1:
        raise ValueError(f"{sheet.title}: the radial stress is not constant ({sorted(sigma_r)} kPa)")
    kept, left_out, last = [], 0, 0.0
    for eps_a, _, q, eps_v in rows:
        eps1 = eps_a * PERCENT
        if eps1 <= last:
            left_out += 1
            continue
        kept.append((eps1, q * KPA, eps_v * PERCENT))
        last = eps1
    p0 = sigma_r.pop() * KPA
    lines = ["# Dobrany sand, drained triaxial compression, sheet " + sheet.title,
             f"# source: {SOURCE}",
             f"# initial void ratio at the start of shear: {void_ratio:.4f}",
             "# test = triaxial_drained",
             f"# p0 = {p0:.6g}",
             "eps1,q,eps_v"]
    lines += [f"{e:.8g},{q:.8g},{v:.8g}" for e, q, v in kept]
    out.write_text("\n".join(lines) + "\n")
    return {"sheet": sheet.title, "file": out.name, "p0_Pa": p0, "void_ratio_start_of_shear": void_ratio,
            "rows_kept": len(kept), "rows_left_out_not_increasing": left_out}


def convert_oedometer(sheet, out: Path) -> dict:
    """Write the oedometric loading-unloading as sigma_a [Pa], eps_a [-]; returns its record."""
    void_ratio = float(sheet.cell(1, 2).value)
    rows = _numeric_rows(sheet, 3)
    lines = ["# Dobrany sand, oedometric loading and unloading of a loose specimen, sheet " + sheet.title,
             f"# source: {SOURCE}",
             f"# initial void ratio: {void_ratio:.4f}",
             "sigma_a,eps_a"]
    lines += [f"{s * KPA:.8g},{e:.8g}" for s, e in rows]
    out.write_text("\n".join(lines) + "\n")
    return {"sheet": sheet.title, "file": out.name, "void_ratio_initial": void_ratio, "rows_kept": len(rows)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workbook", type=Path, help="SoilModels-labProtocol-Sand.xlsx")
    args = parser.parse_args(argv)
    try:
        import openpyxl
    except ImportError:
        print("error: this script needs openpyxl (pip install openpyxl)", file=sys.stderr)
        return 2
    if not args.workbook.is_file():
        print(f"error: {args.workbook}: no such file", file=sys.stderr)
        return 2
    book = openpyxl.load_workbook(args.workbook, data_only=True, read_only=True)
    here = Path(__file__).resolve().parent
    notes = {str(k): v for k, v in book["NOTES"].iter_rows(values_only=True) if k is not None}
    index = book["IDX AND GRAD"]
    records = [convert_cid(book[name], here / file) for name, file in CID_SHEETS.items()]
    records.append(convert_oedometer(book["OED-REC-1"], here / "oed_loose.csv"))
    soil = {"notes": notes, "USCS classification": index.cell(1, 2).value,
            "specific gravity": index.cell(2, 2).value, "angle of repose [deg]": index.cell(5, 2).value}
    (here / "specimens.json").write_text(json.dumps({"source": SOURCE, "soil": soil, "tests": records}, indent=1) + "\n")
    for r in records:
        print(f"{r['sheet']} -> {r['file']}: {r['rows_kept']} rows"
              + (f", {r['rows_left_out_not_increasing']} left out (eps1 not increasing)"
                 if "rows_left_out_not_increasing" in r else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
