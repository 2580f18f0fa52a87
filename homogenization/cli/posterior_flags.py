"""--posterior and --posterior-band of ``hmodel triaxial`` and ``hmodel biaxial``
(``options.add_posterior_arguments``).

- ``apply_posterior(args, argv, parser, dim)``: before any work, reads the posterior
  (``homogenization.calibration.posterior``), refuses (one line, exit 2) a posterior of the other
  dimension, one whose parameters the chosen backends cannot set (the ann runs its model's own
  contact law and cell), and the flags it replaces given explicitly; then sets --law (the
  calibration's, posterior.json's ``contact_law``; none: linear), --phi, --kn and --kt (times
  (p0 / kn_p_ref)^kn_exponent where the calibration ran ``--kn-exponent``) or
  --shear-modulus and --poisson, --alpha0 and --radius to the posterior mean (uncalibrated parameters: the calibration's fixed
  values), and --e-min and --e-max where its data gave void ratios (``check_void_ratio``: then the run
  needs --void-ratio, whose map gives alpha0; ``run_files.resolve_void_ratio``; shifted by the interlocking's state
  map where it has one, ``state_map_bounds``), turns --critical-state on
  where the calibration ran the rule (``critical_state``: the rule at the posterior mean; a posterior of the
  plain cell refuses --critical-state), and draws the band's parameter sets (--posterior-band N);
- ``spread_models(...)``: where the posterior holds alpha0_spread, the analytical model whose cells carry
  the point's families of opening angles (``homogenization.material.opening_spread``); where it holds the
  interlocking friction, the analytical model with per-cell laws that ``interlocking_renewal(...)``'s rule
  (``calibration.interlocking``, at the posterior mean; with the calibration's critical-state renewal inside
  it) steps, as the calibration's forward model does;
- ``run_record(...)``: what run.h5 stores of it;
- ``write_band(...)``: the band by the calibration's forward model, its CSV beside run.h5, and
  its shading in the command's figure.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence, TYPE_CHECKING

import numpy as np

from homogenization.calibration.forward import DENSITY, DENSITY_DEFAULTS, SPREAD, kn_factor, settings_record
from homogenization.cli.run_files import explicit_flags
from homogenization.material import opening_spread
from warp_hcell.core.cli import UserError
from warp_hcell.core.parameters import HertzMindlinLaw, check_alpha0_deg

if TYPE_CHECKING:
    from homogenization.calibration.posterior import PosteriorBand

BAND_FILE = "posterior_band.csv"
"""The band of --posterior-band, written beside run.h5 (columns ``posterior.band_columns``)."""
RULE_TEXT = {2: "{n_orientations} orientations", 3: "Lebedev order {lebedev_order} x {n_spins} spins"}
"""The band's orientation rule in its status line and CSV header, per dimension (``str.format`` of the forward model's
settings)."""
REPLACED_FLAGS = {"phi": "--phi", "kn": "--kn", "kt": "--kt", "alpha0": "--alpha0", "radius": "--radius",
                  "mesostructure": "--mesostructure", "law": "--law", "shear_modulus": "--shear-modulus",
                  "poisson": "--poisson", "e_min": "--e-min", "e_max": "--e-max"}
"""Flags that --posterior sets (or whose cell the calibration did not use): argparse dest -> flag."""


@dataclass
class PosteriorRun:
    """The posterior of a run and, with --posterior-band, its draws (every parameter, shape (N,))."""

    posterior: Any
    draws: dict[str, np.ndarray] | None
    seed: int
    band: PosteriorBand | None = None
    void_ratio: float | None = None
    kn_scale: float = 1.0
    """The factor (p0 / kn_p_ref)^kn_exponent on the posterior's kn at the command's p0 (1 without the exponent)."""

    @property
    def critical_state(self) -> Any:
        """The calibration's critical-state rule at the posterior mean (``CriticalState``), or None."""
        return self.posterior.forward.critical_state

    @property
    def interlocking(self) -> Any:
        """The calibration's interlocking friction at the posterior mean (``Interlocking``), or None."""
        return self.posterior.forward.interlocking


def critical_state(run: PosteriorRun | None, args: argparse.Namespace, dim: int) -> Any:
    """The rule a run applies: the posterior's where it has one, else the defaults' (with --renewal-phases) with
    --critical-state, else None; UserError (one line) for --renewal-phases without a rule of the command's or with
    the posterior's."""
    if run is not None and run.critical_state is not None:
        if args.renewal_phases is not None:
            raise UserError(f"--renewal-phases with --posterior: the posterior's critical-state rule sets its phases "
                            f"({run.critical_state.phases})")
        return run.critical_state
    if not args.critical_state:
        if args.renewal_phases is not None:
            raise UserError("--renewal-phases needs --critical-state (the rule whose renewals it groups)")
        return None
    from homogenization.cli.options import critical_state_rule  # noqa: PLC0415

    return critical_state_rule(dim, args.renewal_phases)


def apply_posterior(args: argparse.Namespace, argv: Sequence[str], parser: argparse.ArgumentParser,
                    dim: int) -> PosteriorRun | None:
    """Read --posterior and set the contact law, alpha0 and radius flags to its mean; None without it.

    Args:
        args: the parsed flags (changed in place).
        argv: the command line, to find the flags given explicitly.
        parser: a fresh parser of the command.
        dim: 2 (biaxial) or 3 (triaxial).

    Raises:
        UserError: one line, before any work (module docstring).
    """
    if args.posterior is None:
        if args.posterior_band is not None:
            raise UserError("--posterior-band needs --posterior (the calibration whose samples it draws)")
        return None
    from homogenization.calibration import posterior as post_mod  # noqa: PLC0415 (h5py, the forward model)

    try:
        post = post_mod.read_posterior(args.posterior)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if dim not in post.dims:
        raise UserError(f"--posterior {post.path}: calibrated on {' and '.join(post_mod.KINDS[d] for d in post.dims)} "
                        f"data; this command runs {post_mod.KINDS[dim]} cells: give a posterior of {post_mod.KINDS[dim]} data")
    if "ann" in args.backend:
        raise UserError("--posterior with --backend ann: the ANN runs its model's own contact law and cell, not the "
                        "posterior's; use analytical or dem")
    given = [flag for dest, flag in REPLACED_FLAGS.items() if dest in explicit_flags(parser, argv, tuple(REPLACED_FLAGS))]
    if given:
        raise UserError(f"{', '.join(given)} conflict with --posterior, which sets the contact law (phi_g and kn, "
                        f"kt/kn or G, nu), alpha0 and the radius of the plain H-cell it was calibrated on; drop them "
                        f"or --posterior")
    law = post.contact_law
    alpha0 = post.mean["alpha0"]
    try:
        check_alpha0_deg(alpha0)
        if SPREAD in post.mean and DENSITY[0] not in post.mean:  # else at --void-ratio's alpha0 (spread_models)
            opening_spread.check(alpha0, post.mean[SPREAD])
    except ValueError as exc:
        raise UserError(f"--posterior {post.path}: {exc}") from None
    if post.forward.interlocking is not None and set(args.backend) - {"analytical"}:
        raise UserError(f"--posterior {post.path}: its interlocking friction runs on the analytical backend only (the "
                        f"DEM's contacts keep phi_g); give --backend analytical")
    if SPREAD in post.mean and set(args.backend) - {"analytical"}:
        raise UserError(f"--posterior {post.path}: its {SPREAD} runs on the analytical backend only (the DEM takes one "
                        f"opening angle per model); give --backend analytical")
    check_void_ratio(post, getattr(args, "void_ratio", None))
    if getattr(args, "critical_state", False) and post.forward.critical_state is None:
        raise UserError(f"--critical-state with --posterior {post.path}: calibrated without the critical-state rule, "
                        f"so its parameters are the plain cell's; drop --critical-state")
    if DENSITY[0] in post.mean:
        args.e_min, args.e_max = state_map_bounds(post, getattr(args, "void_ratio", None), args.p0)
    args.law, args.phi, args.alpha0, args.radius = law.name, law.phi_g_deg, alpha0, post.radius
    scale = kn_factor(args.p0, post.forward) * stiffness_scale(post, getattr(args, "void_ratio", None))
    if law.name == HertzMindlinLaw.name:
        args.shear_modulus, args.poisson = law.shear_modulus, law.poisson
    else:
        args.kn, args.kt = law.kn * scale, law.kt * scale
    draws = None
    if args.posterior_band is not None:
        try:
            draws = post_mod.draw_samples(post, args.posterior_band, args.seed)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    return PosteriorRun(post, draws, args.seed, void_ratio=getattr(args, "void_ratio", None), kn_scale=scale)


def check_void_ratio(post: Any, void_ratio: float | None) -> None:
    """UserError (one line): a posterior whose data gave void ratios (its mean holds e_min and e_max) run
    without --void-ratio or one whose data gave none run with it."""
    mapped = DENSITY[0] in post.mean
    if mapped and void_ratio is None:
        raise UserError(f"--posterior {post.path}: calibrated on data with void ratios (its e_min, e_max map the void "
                        f"ratio to alpha0); give --void-ratio E, the state to run")
    if void_ratio is not None and not mapped:
        raise UserError(f"--void-ratio with --posterior {post.path}: its data gave no void ratios, so its alpha0 is "
                        f"the state; drop --void-ratio")


def stiffness_scale(post: Any, void_ratio: float | None) -> float:
    """The factor [-] on kn of the posterior's interlocking stiffness slope (``interlocking.stiffness_factor``) at
    ``void_ratio``, else at the map's void ratio of the posterior's alpha0 (as ``forward.simulate``); 1 without one."""
    rule = post.forward.interlocking
    if rule is None or rule.stiffness_void_slope == 0.0:
        return 1.0
    from homogenization.calibration.interlocking import stiffness_factor  # noqa: PLC0415
    from homogenization.material.density import default_map  # noqa: PLC0415

    e0 = void_ratio if void_ratio is not None else default_map(3, *(post.mean.get(name, default) for name, default in
                                                                    zip(DENSITY, DENSITY_DEFAULTS))).void_ratio(
        post.mean["alpha0"])
    return float(stiffness_factor(e0, rule.stiffness_void_slope))


def state_map_bounds(post: Any, void_ratio: float | None, p0: float) -> tuple[float, float]:
    """The posterior's e_min and e_max [-] that a run at ``void_ratio`` e0 [-] and confining pressure ``p0`` [Pa] maps
    through: as calibrated, or, where its interlocking has a state-map weight w, both lowered by e_map - e0
    (``interlocking.state_map_void_ratio`` on the posterior mean's line), so that the map's alpha0 of e0 is the
    calibration's of e_map (``forward.density_alpha0``). UserError (one line) where e_map is outside the posterior's
    [e_min, e_max] (the calibration's forward model gives such a set NaN curves)."""
    e_min, e_max = post.mean["e_min"], post.mean["e_max"]
    rule = post.forward.interlocking
    if rule is None or rule.map_state_weight == 0.0 or void_ratio is None:
        return e_min, e_max
    from homogenization.calibration.interlocking import state_map_void_ratio  # noqa: PLC0415

    e_map = float(state_map_void_ratio(void_ratio, p0, rule.map_state_weight, rule.lambda_c, rule.xi, rule.p_ref))
    if not e_min <= e_map <= e_max:
        raise UserError(f"--void-ratio {void_ratio:g} at --p0 {p0:g}: the state map of --posterior {post.path} "
                        f"(map_state_weight {rule.map_state_weight:g}) reads e = {e_map:.4g}, outside its e_min, e_max "
                        f"[{e_min:g}, {e_max:g}]")
    return e_min - (e_map - void_ratio), e_max - (e_map - void_ratio)


def spread_models(run: PosteriorRun | None, models: dict[str, Any], meso: Any, *, lebedev_order: int, n_spins: int,
                  staggered_spins: bool) -> dict[str, Any]:
    """``models`` with the analytical one replaced, where the posterior holds alpha0_spread, by a closed form
    whose cells carry the families of opening angles of one point (``opening_spread.cell_alpha0`` about the
    alpha0 of ``meso``: the posterior mean's, or the map's of --void-ratio; ``FAMILIES_ATTRIBUTE``) for the
    orientation rule of ``meso``, ``lebedev_order`` x ``n_spins``; ``models`` unchanged otherwise. UserError (one
    line) where the lowest family, alpha0 - alpha0_spread, is below the ten-sphere cell's smallest opening."""
    if run is None or (SPREAD not in run.posterior.mean and run.interlocking is None):
        return models
    from homogenization.backends.analytical import Analytical3DCell  # noqa: PLC0415
    from homogenization.element_test.points import orientation_set  # noqa: PLC0415

    mean, law = run.posterior.mean, run.posterior.contact_law
    n = orientation_set(meso, n_orientations=1, lebedev_order=lebedev_order, n_spins=n_spins,
                        staggered_spins=staggered_spins).n_cells
    if SPREAD in mean:
        centre = float(meso.parameters["alpha0_deg"])
        try:
            opening_spread.check(centre, mean[SPREAD])
        except ValueError as exc:
            raise UserError(f"--posterior {run.posterior.path} at alpha0 {centre:.4g} deg: {exc}") from None
        alpha0 = opening_spread.cell_alpha0(np.array([centre]), np.array([mean[SPREAD]]), n)
    else:  # the interlocking friction: per-cell laws at the cell's own alpha0 (the void ratio's, where given)
        alpha0 = np.full(n, float(meso.parameters["alpha0_deg"]))
    ones = np.ones(alpha0.size)
    if law.name == HertzMindlinLaw.name:
        model = Analytical3DCell.with_hertz_cell_laws(law.shear_modulus * ones, law.poisson * ones, law.phi_g_deg * ones,
                                                      run.posterior.radius, alpha0_deg=alpha0)
    else:
        model = Analytical3DCell.with_cell_laws(law.kn * run.kn_scale * ones, law.kt_over_kn * ones, law.phi_g_deg * ones,
                                                run.posterior.radius, alpha0_deg=alpha0)
    if SPREAD in mean:
        setattr(model, opening_spread.FAMILIES_ATTRIBUTE, True)
    return {**models, "analytical": model}


def interlocking_renewal(run: PosteriorRun | None, meso: Any, critical_state: Any, void_ratio: float | None) -> Any:
    """``driver.run``'s ``renewal`` where the posterior holds the interlocking friction or alpha0_spread: a callable
    that puts on a run's points (one point, ``spread_models``' per-cell model) the calibration's
    ``InterlockingFriction`` at the posterior mean (where it has one), wrapping its critical-state renewal
    (``critical_state``; a ``PopulationRenewal`` on the posterior's e_min, e_max, each family of a spread renewed on
    its own void ratio) where it has one; e0 = ``void_ratio``, else the map's void ratio of the cell's alpha0, as in
    ``forward.simulate``. None without the friction and without a spread renewed."""
    spread = run is not None and SPREAD in run.posterior.mean
    if run is None or (run.interlocking is None and not (spread and critical_state is not None)):
        return None
    from homogenization.calibration.forward import full_parameters  # noqa: PLC0415
    from homogenization.calibration.interlocking import InterlockingFriction  # noqa: PLC0415
    from homogenization.calibration.renewal import PopulationRenewal, laws_of  # noqa: PLC0415
    from homogenization.material.density import default_map  # noqa: PLC0415

    post = run.posterior
    alpha0 = np.array([float(meso.parameters["alpha0_deg"])])
    full = full_parameters({name: np.array([value]) for name, value in post.mean.items()}, post.forward)
    if "kn" in full:
        full["kn"] = full["kn"] * run.kn_scale
    e_min, e_max = (np.array([post.mean.get(name, default)]) for name, default in zip(DENSITY, DENSITY_DEFAULTS))
    e0 = np.array([void_ratio if void_ratio is not None else
                   default_map(3, e_min[0], e_max[0]).void_ratio(alpha0[0])])

    def build(points: Any) -> Any:
        inner = None
        if critical_state is not None:
            inner = PopulationRenewal(critical_state, points.material, points.state, default_map(3), alpha0,
                                      laws_of(full, post.forward.law), post.forward.law, post.radius,
                                      e_bounds=(e_min, e_max), spread_deg=full.get(SPREAD))
        if run.interlocking is None:
            return inner
        return InterlockingFriction(run.interlocking, points.material, points.state, full["phi_g"], e0, inner=inner,
                                    families=opening_spread.N_NODES if SPREAD in full else 1)

    return build


def check_band_test(run: PosteriorRun | None, settings: Mapping[str, Any], what: str) -> None:
    """UserError (one line) where --posterior-band is asked of a run that is not a built-in drained or
    undrained test (``settings``: the command's resolved programme settings); ``what`` names the
    command's other settings the band cannot follow (e.g. "--fabric-anisotropy"), "" if none."""
    if run is None or run.draws is None:
        return
    if "programme_file" in settings or settings.get("test", "undrained") not in ("undrained", "drained") or what:
        raise UserError(f"--posterior-band runs the built-in drained or undrained test only"
                        f"{' (not with ' + what + ')' if what else ''}; drop --posterior-band or the other test")


def run_record(run: PosteriorRun | None) -> dict[str, Any]:
    """``{"posterior": ...}`` for run.h5's parameters (``CalibratedPosterior.record`` and the band's
    draws, seed, file and forward model); {} without --posterior."""
    if run is None:
        return {}
    record = run.posterior.record()
    if run.draws is not None:
        record["band"] = {"draws": int(next(iter(run.draws.values())).size), "seed": run.seed, "file": BAND_FILE,
                          "quantiles": [0.025, 0.975],
                          "forward_model": settings_record(run.posterior.forward)}
    return {"posterior": record}


def compute_band(run: PosteriorRun | None, *, dim: int, drained: bool, p0: float, eps_max: float) -> None:
    """The band of ``run`` (``posterior.band``), kept in ``run.band``; nothing without --posterior-band."""
    if run is None or run.draws is None:
        return
    from homogenization.calibration.posterior import band  # noqa: PLC0415

    run.band = band(run.posterior, run.draws, dim=dim, drained=drained, p0=p0, eps_max=eps_max,
                    void_ratio=run.void_ratio)


def write_band(run: PosteriorRun | None, work: Path) -> str | None:
    """posterior_band.csv into ``work`` (the folder being written); its status line, or None."""
    if run is None or run.band is None:
        return None
    from homogenization.calibration.posterior import write_band_csv  # noqa: PLC0415

    b, f = run.band, run.posterior.forward
    rule = RULE_TEXT[b.dim].format(n_orientations=f.n_orientations, lebedev_order=f.lebedev_order, n_spins=f.n_spins)
    write_band_csv(work / BAND_FILE, b, {
        "posterior": run.posterior.path.resolve(), "draws": b.n_sets, "seed": run.seed,
        "failed_draws": b.n_failed, "forward_fallbacks": b.n_fallback, "interlocking_clips": b.n_clip,
        "renewal_clips": b.n_renewal_clip,
        "forward_model": f"closed form of the calibration: {rule}, increment {f.increment:g}, "
                         f"iso increment {f.iso_increment:g}, stress rtol {f.stress_rtol:g}",
        "columns": "q, p [N/m in 2D, Pa in 3D]; eps_v = sum of the normal strains since the end of stage 1 [-]; "
                   "lo, hi: 2.5 and 97.5 % quantiles over the draws; forward_at_mean: the same forward model at "
                   "the posterior mean",
    })
    return (f"posterior band: {b.n_sets} draws ({b.n_failed} failed, {b.n_fallback} forward fallbacks, "
            f"clips: interlocking {b.n_clip}, renewal {b.n_renewal_clip}), "
            f"calibration's forward model ({rule}) -> {BAND_FILE}")


def shade(fig, run: PosteriorRun | None, panels: Sequence[tuple[int, str, float]]) -> None:
    """Shade the band in ``fig``'s panels and add it to the figure's legend.

    Args:
        panels: (axes index, channel, scale) per panel whose x axis is eps1 in % and whose y axis
            shows ``scale`` x the channel (e.g. 100 for eps_v in %).
    """
    if run is None or run.band is None:
        return
    from homogenization.output.figure_style import figure_legend  # noqa: PLC0415

    b = run.band
    x = 100.0 * b.eps1
    patch = None
    for index, channel, scale in panels:
        ax = fig.axes[index]
        patch = ax.fill_between(x, scale * b.columns[f"{channel}_lo"], scale * b.columns[f"{channel}_hi"], color="0.5",
                                alpha=0.3, lw=0,
                                label=f"posterior 95 % band ({b.n_sets} draws, calibration's forward model)")
    handles = []
    for legend in list(fig.legends):
        for handle, text in zip(legend.legend_handles, legend.get_texts()):
            handle.set_label(text.get_text())
            handles.append(handle)
        legend.remove()
    figure_legend(fig, handles + [patch])
