"""A calibration's posterior read back, to run the H-model at it: ``hmodel triaxial --posterior`` and
``hmodel biaxial --posterior``.

``read_posterior(path)`` reads what ``hmodel calibrate`` wrote into its folder: posterior.json
(mean, median, ci95 of each calibrated parameter in the CLI flags' units: phi_g and alpha0 [deg],
kn [N/m], kt_over_kn [-]), run.json beside it (the values of the parameters not calibrated, the
grain radius, the forward model's settings and the dimension of the data) and posterior.h5 (the
retained samples, ``/samples/<name>``). ``band(...)`` runs the batched closed form
(``forward.simulate``) for parameter sets drawn from those samples and returns the 2.5 and 97.5 %
quantiles of q, p and eps_v over eps1. Where the calibration corrected its forward model
(``resolution``: the reference's difference added to every curve), the band does the same at its own
test: the reference's curve minus the model's at the posterior mean is added to every draw.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from homogenization.calibration.data import Measurement
from homogenization.calibration.bayes import UNITS
from homogenization.calibration.forward import (
    CONTACT_LAW_KEY,
    CRITICAL_STATE_KEY,
    DENSITY,
    INTERLOCKING,
    KN_EXPONENT,
    INTERLOCKING_KEY,
    RULE,
    LAW_PARAMETERS,
    SPREAD,
    calibratable,
    ForwardSettings,
    contact_law_at,
    simulate,
)
from homogenization.calibration.interlocking import Interlocking
from homogenization.material.critical_state import CriticalState
from warp_hcell.core.parameters import ContactLaw, Law, contact_law_from_dict

POSTERIOR_FILE = "posterior.json"
SAMPLES_FILE = "posterior.h5"
RUN_FILE = "run.json"
BAND_POINTS = 200
"""Most eps1 values at which the band is tabulated [-]."""
BAND_QUANTILES = (0.025, 0.975)
"""Quantiles of the band [-]: a 95 % band."""
KINDS = {2: "biaxial (2D)", 3: "triaxial (3D)"}


@dataclass(frozen=True)
class CalibratedPosterior:
    """A calibration's posterior, read back.

    Attributes:
        path: the posterior.json read.
        sha256: its sha256 (recorded in run.h5).
        dims: the dimensions of the calibration's data (2: biaxial, 3: triaxial), sorted.
        calibrated: the calibrated parameters, in posterior.json's order.
        mean: every parameter of the calibration's contact law (``forward.parameters``), and alpha0_spread
            where calibrated or fixed nonzero, e_min and e_max where its data gave void ratios, at the
            posterior mean (calibrated) or at the calibration's fixed value (not calibrated), CLI units.
        radius: the grain radius of the calibration [m].
        forward: the calibration's forward-model settings (the band runs with them).
        reference: where the calibration corrected its forward model, the reference model (``forward`` with
            the reference's increments and orientations); None otherwise.
    """

    path: Path
    sha256: str
    dims: tuple[int, ...]
    calibrated: tuple[str, ...]
    mean: dict[str, float]
    radius: float
    forward: ForwardSettings
    reference: ForwardSettings | None = None

    @property
    def contact_law(self) -> Law:
        """The contact law at the posterior mean (the calibration's law: linear or Hertz-Mindlin)."""
        return contact_law_at({name: np.array([value]) for name, value in self.mean.items()}, 0, self.forward.law)

    def record(self) -> dict[str, Any]:
        """What run.h5 stores of the posterior (its ``parameters`` attribute, key ``posterior``)."""
        return {"file": str(self.path.resolve()), "sha256": self.sha256, "statistic": "mean",
                "calibrated": list(self.calibrated), "values": dict(self.mean),
                "units": {name: UNITS[name] for name in self.mean},
                **({} if self.forward.law == ContactLaw.name else {"contact_law": self.contact_law.to_dict()})}


def _read_json(path: Path, what: str) -> Any:
    if not path.is_file():
        raise ValueError(f"--posterior {path}: no such file" if what == "posterior" else
                         f"--posterior: no {path.name} beside it in {path.parent} (the folder of an hmodel calibrate run)")
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"--posterior: cannot read {path}: {exc}") from None


def _checked_record(data: dict, key: str, record: type, what: str, path: Path) -> Any:
    """``record(**data.pop(key))`` after its ``check()``, or None where ``data`` has no ``key``; ValueError (one
    line naming ``path`` and ``what`` it should be) where the entry does not make a valid record."""
    if key not in data:
        return None
    try:
        value = record(**data.pop(key))
        value.check()
    except (TypeError, ValueError) as exc:
        raise ValueError(f"--posterior {path}: {key!r} is not {what}: {exc}") from None
    return value


def read_posterior(path: Path) -> CalibratedPosterior:
    """The posterior of ``path`` (posterior.json, or the folder holding it) and its run.json.

    Raises:
        ValueError: one line for a missing or malformed file, a parameter not of its contact law,
            or a run.json without the calibration's dimension, fixed values or radius.
    """
    from warp_hcell.core.provenance import file_sha256  # noqa: PLC0415

    path = Path(path)
    if path.is_dir():
        path = path / POSTERIOR_FILE
    data = _read_json(path, "posterior")
    if not isinstance(data, dict) or not data:
        raise ValueError(f"--posterior {path}: not a posterior.json of hmodel calibrate (parameter -> mean, median, ci95)")
    law_name = ContactLaw.name
    if CONTACT_LAW_KEY in data:
        try:
            law_name = contact_law_from_dict(data.pop(CONTACT_LAW_KEY)).name
        except (TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"--posterior {path}: {CONTACT_LAW_KEY!r} is not a contact law: {exc}") from None
    rule = _checked_record(data, CRITICAL_STATE_KEY, CriticalState, "a critical-state rule", path)
    interlocking = _checked_record(data, INTERLOCKING_KEY, Interlocking, "an interlocking friction", path)
    mean: dict[str, float] = {}
    for name, entry in data.items():
        if name not in calibratable(law_name):
            raise ValueError(f"--posterior {path}: {name!r} is not a parameter of the {law_name} contact law "
                             f"({', '.join(calibratable(law_name))})")
        value = entry.get("mean") if isinstance(entry, dict) else None
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"--posterior {path}: {name!r} has no finite mean")
        mean[name] = float(value)
    run = _read_json(path.parent / RUN_FILE, "run")
    try:
        forward_json = run["config"]["forward"]
        dims = tuple(sorted({int(d) for d in run["data_dimensions"]}))
        fixed = {name: float(forward_json["fixed"][name]) for name in LAW_PARAMETERS[law_name]}
        for name in (SPREAD, *DENSITY):
            if name in forward_json["fixed"]:
                fixed[name] = float(forward_json["fixed"][name])
        radius = float(forward_json["radius"])
        fields = {k: v for k, v in forward_json.items() if k in ForwardSettings.__dataclass_fields__}
        forward = ForwardSettings(**{**fields, "law": law_name, "fixed": fixed, "backend": "analytical",
                                     "backend_options": {}, "critical_state": rule, "interlocking": interlocking})
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"--posterior: {path.parent / RUN_FILE} lacks {exc} (written by an older hmodel calibrate? "
                         f"rerun the same calibrate command on {path.parent} to rewrite it)") from None
    if KN_EXPONENT in mean:  # calibrated: the replay (kn_factor) runs the mean's exponent
        forward = replace(forward, kn_exponent=mean[KN_EXPONENT])
    names = forward.parameters + tuple(name for name in (SPREAD, *DENSITY, *RULE, *INTERLOCKING, KN_EXPONENT)
                                       if name in mean or name in fixed)
    return CalibratedPosterior(path=path, sha256=file_sha256(path), dims=dims, calibrated=tuple(mean),
                               mean={name: mean.get(name, fixed.get(name)) for name in names}, radius=radius,
                               forward=forward, reference=_reference(run, forward))


def _reference(run: Any, forward: ForwardSettings) -> ForwardSettings | None:
    """The reference model of run.json's ``forward_model.resolution`` where the calibration corrected its
    forward model with it (``corrected_at`` recorded); None otherwise."""
    record = run.get("forward_model", {}).get("resolution", {}) if isinstance(run, dict) else {}
    knobs = record.get("reference") if isinstance(record, dict) else None
    if not isinstance(knobs, dict) or record.get("corrected_at") is None:
        return None
    return replace(forward, **{k: v for k, v in knobs.items() if k in ForwardSettings.__dataclass_fields__})


def draw_samples(post: CalibratedPosterior, n: int, seed: int) -> dict[str, np.ndarray]:
    """``n`` parameter sets drawn without replacement from posterior.h5's samples (seeded): every
    parameter of the calibration's law (``forward.parameters``) as shape (n,), the uncalibrated ones at
    their fixed values.

    Raises:
        ValueError: a missing or malformed posterior.h5, or fewer samples than ``n`` (one line).
    """
    import h5py  # noqa: PLC0415

    path = post.path.parent / SAMPLES_FILE
    if not path.is_file():
        raise ValueError(f"--posterior-band: no {SAMPLES_FILE} beside {post.path}")
    try:
        with h5py.File(path, "r") as fh:
            samples = {name: np.asarray(fh[f"samples/{name}"][()], dtype=np.float64) for name in post.calibrated}
    except (OSError, KeyError) as exc:
        raise ValueError(f"--posterior-band: cannot read the samples of {path}: {exc}") from None
    size = min(v.size for v in samples.values())
    if size < n:
        raise ValueError(f"--posterior-band {n}: {path} holds {size} samples; ask for at most that many")
    pick = np.random.default_rng(seed).choice(size, size=n, replace=False)
    return {name: samples[name][pick] if name in samples else np.full(n, post.mean[name]) for name in post.mean}


def band_grid(eps_max: float, increment: float) -> np.ndarray:
    """eps1 values of the band: multiples of ``increment`` up to ``eps_max``, at most ``BAND_POINTS`` of them."""
    n = max(1, math.floor(eps_max / increment + 1e-9))
    steps = np.unique(np.round(np.linspace(1, n, min(n, BAND_POINTS))).astype(int))
    return steps * increment


@dataclass(frozen=True)
class PosteriorBand:
    """The posterior band of a built-in test (``band``).

    Attributes:
        eps1: shear strain of each row [-], shape (k,).
        columns: ``<channel>_lo`` / ``_median`` / ``_hi`` for q, p [N/m or Pa] and eps_v [-] (the sum of the normal
            strains since the end of stage 1, contraction positive), quantiles over the sets whose curve is finite,
            and ``<channel>_forward_at_mean`` (the forward model at the posterior mean), each shape (k,).
        dim: the test's dimension.
        n_sets, n_failed: sets drawn; sets whose isotropic stage did not reach p0.
        n_fallback, n_clip, n_renewal_clip: the forward model's fallbacks and its rules' clips (``forward.Curves``).
        correction: None, or (``post.reference`` set) channel -> the largest abs difference reference - model at
            the mean, added to every curve; ``reference`` its settings.
    """

    eps1: np.ndarray
    columns: dict[str, np.ndarray]
    dim: int
    n_sets: int
    n_failed: int
    n_fallback: int
    n_clip: int
    n_renewal_clip: int
    correction: dict[str, float] | None = None
    reference: ForwardSettings | None = None


def band(post: CalibratedPosterior, params: Mapping[str, np.ndarray], *, dim: int, drained: bool, p0: float,
         eps_max: float, void_ratio: float | None = None) -> PosteriorBand:
    """The posterior band (``PosteriorBand``) of a built-in test (isotropic compression to ``p0``, then drained or
    constant-volume shear to ``eps_max``; at ``void_ratio``, each set's map's alpha0, where given) by the
    calibration's forward model (``post.forward``), all sets in one batch."""
    eps1 = band_grid(eps_max, post.forward.increment)
    test = Measurement("band", post.path, drained, p0, eps1, {}, dim, void_ratio)
    n = int(next(iter(params.values())).size)
    with_mean = {name: np.append(params[name], post.mean[name]) for name in post.mean}
    with np.errstate(all="ignore"):  # a diverging set gives NaN, left out of the quantiles and counted
        curves = simulate(test, with_mean, post.forward)
    shift: dict[str, np.ndarray] = {}
    if post.reference is not None:
        with np.errstate(all="ignore"):
            fine = simulate(test, {name: np.array([value]) for name, value in post.mean.items()}, post.reference)
        shift = {c: np.nan_to_num(fine.channel(c)[0] - curves.channel(c)[n]) for c in ("q", "p", "eps_v")}
    ok = np.all(np.isfinite(curves.q[:n]) & np.isfinite(curves.p[:n]) & np.isfinite(curves.eps_v[:n]), axis=1)
    columns: dict[str, np.ndarray] = {}
    for c in ("q", "p", "eps_v"):
        values = curves.channel(c) + shift.get(c, 0.0)
        lo, med, hi = (np.quantile(values[:n][ok], q, axis=0) if ok.any() else np.full(eps1.size, np.nan)
                       for q in (BAND_QUANTILES[0], 0.5, BAND_QUANTILES[1]))
        columns[f"{c}_lo"], columns[f"{c}_median"], columns[f"{c}_hi"] = lo, med, hi
        columns[f"{c}_forward_at_mean"] = values[n]
    return PosteriorBand(eps1, columns, dim, n, int(np.count_nonzero(~ok)), int(curves.n_fallback.sum()),
                int(curves.n_clip.sum()), int(curves.n_renewal_clip.sum()),
                {c: float(np.max(np.abs(v))) for c, v in shift.items()} or None, post.reference)


def band_columns() -> list[str]:
    """Columns of the band's CSV (``write_band_csv``)."""
    return ["eps1"] + [f"{c}_{s}" for c in ("q", "p", "eps_v") for s in ("lo", "median", "hi", "forward_at_mean")]


def write_band_csv(path: Path, result: PosteriorBand, header: Mapping[str, Any]) -> None:
    """``result`` of ``band`` as CSV (atomically), ``# key = value`` comment lines first."""
    from warp_hcell.core.files import atomic_write  # noqa: PLC0415

    columns = band_columns()
    lines = [f"# {k} = {v}" for k, v in header.items()]
    if result.correction is not None:
        ref = result.reference
        lines.append(f"# resolution_correction = the calibration's reference (increment {ref.increment:g}, iso "
                     f"increment {ref.iso_increment:g}, {ref.n_orientations} orientations (2D) / Lebedev "
                     f"{ref.lebedev_order} x {ref.n_spins} spins (3D)) "
                     f"minus the forward model at the posterior mean, added to every draw; largest abs value: "
                     + ", ".join(f"{c} {v:.4g}" for c, v in result.correction.items()))
    lines.append(",".join(columns))
    table = np.stack([result.eps1] + [result.columns[c] for c in columns[1:]], axis=1)
    lines += [",".join(f"{v:.10g}" for v in row) for row in table.tolist()]
    with atomic_write(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
