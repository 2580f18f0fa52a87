"""Physical constants and numerical defaults, in one place.

Every default of the package and of its command-line interfaces is read from the frozen
dataclasses below (specification: docs/model.md, sections 1 and 10). No default
value is typed twice: CLIs build their ``default=`` from these objects.

Units: SI, 2D (forces per unit length for stresses, N/m). Angles carry the suffix ``_deg``
when in degrees; code works in radians internally. Sign convention: compression and
contraction positive.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, ClassVar, Mapping, Union

ALPHA_MIN_DEG = 30.0
"""Smallest admissible opening angle [deg]: lateral grains 2-6 and 3-5 touch."""
ALPHA_MAX_DEG = 90.0
"""Opening angle [deg] at which grains 1-4 touch; initial states need alpha0 < 90."""

ALPHA_MIN_3D_DEG = 45.0
"""Smallest opening angle [deg] of the ten-sphere cell of equal spheres in orthogonal planes:
below, the lateral grains of its two planes overlap."""

PRIOR_BOUNDS_2D: dict[str, tuple[float, float, bool]] = {
    "phi_g": (10.0, 45.0, False),
    "kn": (5e7, 5e9, True),
    "kt_over_kn": (0.1, 1.5, False),
    "alpha0": (35.0, 85.0, False),
}
"""Default prior of ``hmodel calibrate`` on biaxial (2D) data, per micro-parameter: (low, high,
log-uniform?) in the CLI flags' units (phi_g, alpha0 [deg], kn [N/m], kt_over_kn [-]); uniform in
the value, or in its log10 where log-uniform. kn spans 8.5 to 850 x the default p0 of 5.85e6 N/m."""
PRIOR_BOUNDS_3D: dict[str, tuple[float, float, bool]] = {
    "phi_g": (10.0, 45.0, False),
    "kn": (1e6, 1e10, True),
    "kt_over_kn": (0.1, 1.5, False),
    "alpha0": (ALPHA_MIN_3D_DEG, 85.0, False),
}
"""Default prior of ``hmodel calibrate`` on triaxial (3D) data (and on 2D and 3D data fitted
together), as ``PRIOR_BOUNDS_2D``: alpha0 from ``ALPHA_MIN_3D_DEG``, which the ten-sphere cell
needs; kn from 1e6 to 1e10 N/m, which at laboratory pressures (p0 = 5e4 to 1e6 Pa, grain radius
0.5 m) spans peak stress ratios q/p0 from below 1 to above 10 (the closed form at phi_g = 30 deg,
alpha0 = 60 deg, drained at 1e5 Pa: q_peak / p0 = 0.9, 2.6, 5.1, 12.3 at kn = 1e6, 1e7, 1e8, 1e9)."""


PRIOR_BOUNDS_HERTZ_3D: dict[str, tuple[float, float, bool]] = {
    "shear_modulus": (1e6, 1e11, True),
    "poisson": (0.0, 0.45, False),
}
"""Prior bounds of the Hertz-Mindlin law's parameters on triaxial data, as ``PRIOR_BOUNDS_3D``: the grain
shear modulus G [Pa] log-uniform from 1 MPa to 100 GPa (the closed form's drained tests of Dobrany sand
come nearest its measured curves near G = 2 GPa, below the mineral's 29-44 GPa, where the model's peak
q / p0 is 12-18: the H-cell's stiffness, not the mineral's; docs/calibration.md), the Poisson ratio nu
[-] uniform in [0, 0.45]; phi_g and alpha0 as in ``PRIOR_BOUNDS_3D``. The default prior of ``hmodel
calibrate --law hertz-mindlin``."""


def check_alpha0_deg(alpha0_deg: float) -> float:
    """Return ``alpha0_deg`` as float if it lies in [30, 90) deg, else raise ValueError (one line)."""
    value = float(alpha0_deg)
    if not (ALPHA_MIN_DEG <= value < ALPHA_MAX_DEG):
        raise ValueError(f"alpha0 = {value:g} deg is outside [{ALPHA_MIN_DEG:g}, {ALPHA_MAX_DEG:g}) deg")
    return value


def check_positive(name: str, value: float) -> float:
    """Return ``value`` as float if finite and > 0, else raise ValueError naming ``name``."""
    value = float(value)
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} = {value:g} must be finite and > 0")
    return value


@dataclass(frozen=True)
class LawFlag:
    """A command-line flag of a contact law's parameter (``warp_hcell.core.cli.add_contact_law_arguments``
    builds the flags of every law of ``CONTACT_LAWS`` from these)."""

    flag: str
    """The flag, e.g. "--kn"; laws that share a parameter declare the same flag."""
    parameter: str
    """The keyword of the law's ``from_flags`` it sets; its default is the law's field of that name (none:
    the flag has no default)."""
    help: str
    """What it sets, with its unit and range."""
    positive: bool = False
    """True: a value must be > 0; False: any finite value (the law's ranges are checked on building it)."""


FRICTION_FLAG = LawFlag("--phi", "phi_g_deg", "inter-granular friction angle phi_g [deg], in [0, 90)")
"""--phi: the friction angle, a flag of every law."""


@dataclass(frozen=True)
class ContactLaw:
    """Linear contact law with Coulomb friction (the default law of every backend): f_n = kn overlap,
    tangential spring of stiffness kt capped at mu f_n."""

    kn: float = 2e8
    """Normal contact stiffness [N/m]."""
    kt_over_kn: float = 0.5
    """Tangential to normal stiffness ratio [-]."""
    phi_g_deg: float = 30.0
    """Inter-granular friction angle [deg]."""

    def __post_init__(self) -> None:
        check_positive("kn", self.kn)
        check_positive("kt_over_kn", self.kt_over_kn)
        if not (0.0 <= self.phi_g_deg < 90.0):
            raise ValueError(f"phi_g = {self.phi_g_deg:g} deg is outside [0, 90) deg")

    name: ClassVar[str] = "linear"
    summary: ClassVar[str] = "linear springs"
    """What the law is, for the help of --law."""
    planar: ClassVar[bool] = True
    """True: defined for disks (planar cells) as well as spheres."""
    flags: ClassVar[tuple[LawFlag, ...]] = (
        LawFlag("--kn", "kn", "normal contact stiffness [N/m]", positive=True),
        LawFlag("--kt", "kt", f"tangential contact stiffness [N/m] (default: {kt_over_kn:g} x kn)", positive=True),
        FRICTION_FLAG,
    )
    """The law's command-line flags (``LawFlag``)."""

    @classmethod
    def from_flags(cls, kn: float, phi_g_deg: float, kt: float | None = None) -> "ContactLaw":
        """The law of its flags: kt [N/m] (None: ``kt_over_kn`` x kn) sets ``kt_over_kn`` = kt / kn."""
        kt = cls.kt_over_kn * kn if kt is None else kt
        return cls(kn=kn, kt_over_kn=kt / kn, phi_g_deg=phi_g_deg)

    @property
    def kt(self) -> float:
        """Tangential contact stiffness [N/m]."""
        return self.kt_over_kn * self.kn

    def to_dict(self) -> dict[str, float]:
        """The law as file formats store it (no ``law`` key: the linear law is the default)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "ContactLaw":
        """The law of its ``to_dict`` (a ``law`` key, if any, must name this law).

        Raises:
            ValueError: (one line) another law's name, or a key the law does not have.
        """
        return _law_from_dict(cls, values)

    @property
    def mu(self) -> float:
        """Friction coefficient tan(phi_g) [-]."""
        return math.tan(math.radians(self.phi_g_deg))


def hertz_normal_modulus(shear_modulus, poisson):
    """(4/3) E* [Pa] of a Hertz contact of two grains of shear modulus G [Pa] and Poisson ratio nu [-],
    E* = G / (1 - nu) (floats or arrays, elementwise)."""
    return 4.0 / 3.0 * (shear_modulus / (1.0 - poisson))


def hertz_shear_stiffness_modulus(shear_modulus, poisson):
    """8 G* [Pa] of a Mindlin contact of two grains of shear modulus G [Pa] and Poisson ratio nu [-],
    G* = G / (2 (2 - nu)) (floats or arrays, elementwise)."""
    return 8.0 * (shear_modulus / (2.0 * (2.0 - poisson)))


@dataclass(frozen=True)
class HertzMindlinLaw:
    """Hertz-Mindlin contact law of elastic spheres with Coulomb friction (docs/model.md, "Contact laws").

    For a pair of spheres of radii r_i, r_j with overlap delta = r_i + r_j - distance [m]:

        N = (4/3) E* sqrt(R*) delta^(3/2)  [N],   kt = 8 G* sqrt(R* delta)  [N/m],

    R* = r_i r_j / (r_i + r_j), E* = G / (1 - nu) (= E / (2 (1 - nu^2)), E = 2 G (1 + nu)) and
    G* = G / (2 (2 - nu)) for grains of one material. The tangential spring grows by kt times
    the tangential relative displacement (kt at the current overlap) and is capped at mu N, as
    in the linear law (no Mindlin-Deresiewicz partial slip). It is the law of YADE's
    Ip2_FrictMat_FrictMat_MindlinPhys / Law2_ScGeom_MindlinPhys_Mindlin without damping or
    adhesion (FrictMat young = E, poisson = nu). Defined for spheres (3D cells) only.
    """

    name: ClassVar[str] = "hertz-mindlin"
    summary: ClassVar[str] = "Hertz-Mindlin of elastic spheres"
    """What the law is, for the help of --law."""
    planar: ClassVar[bool] = False
    """Defined for spheres (3D cells) only."""
    flags: ClassVar[tuple[LawFlag, ...]] = (
        LawFlag("--shear-modulus", "shear_modulus", "Hertz-Mindlin: shear modulus G of the grain material [Pa]",
                positive=True),
        LawFlag("--poisson", "poisson", "Hertz-Mindlin: Poisson ratio nu of the grain material [-], in [0, 0.5)"),
        FRICTION_FLAG,
    )
    """The law's command-line flags (``LawFlag``)."""
    shear_modulus: float = 29e9
    """Shear modulus G of the grain material [Pa] (quartz sand in DEM practice: about 29 GPa)."""
    poisson: float = 0.2
    """Poisson ratio nu of the grain material [-], in [0, 0.5)."""
    phi_g_deg: float = 30.0
    """Inter-granular friction angle [deg]."""

    def __post_init__(self) -> None:
        check_positive("shear_modulus", self.shear_modulus)
        if not (0.0 <= self.poisson < 0.5):
            raise ValueError(f"poisson = {self.poisson:g} is outside [0, 0.5)")
        if not (0.0 <= self.phi_g_deg < 90.0):
            raise ValueError(f"phi_g = {self.phi_g_deg:g} deg is outside [0, 90) deg")

    @classmethod
    def from_flags(cls, **values: float) -> "HertzMindlinLaw":
        """The law of its flags (keywords: its fields)."""
        return cls(**values)

    @property
    def normal_modulus(self) -> float:
        """(4/3) E* [Pa]: N = normal_modulus sqrt(R*) delta^(3/2) (``hertz_normal_modulus``)."""
        return hertz_normal_modulus(self.shear_modulus, self.poisson)

    @property
    def shear_stiffness_modulus(self) -> float:
        """8 G* [Pa]: kt = shear_stiffness_modulus sqrt(R* delta) (``hertz_shear_stiffness_modulus``)."""
        return hertz_shear_stiffness_modulus(self.shear_modulus, self.poisson)

    @property
    def mu(self) -> float:
        """Friction coefficient tan(phi_g) [-]."""
        return math.tan(math.radians(self.phi_g_deg))

    def to_dict(self) -> dict[str, float | str]:
        """The law as file formats store it: {"law": name, field: value, ...}."""
        return {"law": self.name, **asdict(self)}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "HertzMindlinLaw":
        """The law of its ``to_dict`` (``ContactLaw.from_dict``)."""
        return _law_from_dict(cls, values)


Law = Union[ContactLaw, HertzMindlinLaw]
"""Any contact-law declaration of ``CONTACT_LAWS``."""
CONTACT_LAWS: dict[str, type] = {ContactLaw.name: ContactLaw, HertzMindlinLaw.name: HertzMindlinLaw}
"""Contact laws by name (the ``law`` key of files; a mapping without it is the linear law)."""
HERTZ_DT_OVERLAP = 2e-3
"""Overlap, as a fraction of r_i + r_j, at whose Hertz tangent stiffness the meso-DEM sets its time
step and force floor [-] (the linear law's kn). Drained triaxial tests at 50-200 kPa on grains with
G = 29 GPa reach overlaps of about 1e-4 to 5e-4 (r_i + r_j); a contact stiffer than this one
(overlap above 2e-3 (r_i + r_j)) is counted in the DEM's ``n_stiffer_than_dt`` diagnostic."""


def _law_from_dict(cls: type, values: Mapping[str, Any]) -> Any:
    """Law ``cls`` of mapping ``values`` (its fields; ``law`` its name or absent for the linear law)."""
    values = dict(values)
    name = values.pop("law", ContactLaw.name)
    if name != cls.name:
        raise ValueError(f"contact law {name!r} is not the {cls.name!r} law")
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"contact law {name!r} has no parameter {unknown[0]!r}; it has {', '.join(sorted(known))}")
    return cls(**values)


def contact_law_from_dict(values: Mapping[str, Any]) -> Law:
    """The contact law a file stores (``to_dict`` of any law; no ``law`` key: the linear law).

    Raises:
        ValueError: (one line) an unknown law name or a key the law does not have.
    """
    name = values.get("law", ContactLaw.name)
    if name not in CONTACT_LAWS:
        raise ValueError(f"unknown contact law {name!r}; choose from {', '.join(CONTACT_LAWS)}")
    return CONTACT_LAWS[name].from_dict(values)


def require_linear_law(law: Any, what: str) -> None:
    """ValueError (one line) unless ``law`` is the linear law: ``what`` (e.g. "the meso-ANN backend")
    was built for the linear law only."""
    name = getattr(law, "name", ContactLaw.name)
    if name != ContactLaw.name:
        raise ValueError(f"{what} supports the linear contact law only, not {name!r}")


@dataclass(frozen=True)
class CellDefaults:
    """Defaults of the H-cell and of the orientation set (spec section 1)."""

    radius: float = 0.5
    """Grain radius r [m] (diameter D = 2 r)."""
    alpha0_deg: float = 55.0
    """Initial opening angle [deg], admissible range [30, 90)."""
    n_orientations: int = 360
    """Number of cell orientations theta_k = k pi / N [-]."""
    p0: float = 5.85e6
    """Confining pressure of the isotropic stage [N/m], compression positive."""

    def __post_init__(self) -> None:
        check_positive("radius", self.radius)
        check_alpha0_deg(self.alpha0_deg)
        check_positive("p0", self.p0)
        if int(self.n_orientations) < 1:
            raise ValueError(f"n_orientations = {self.n_orientations} must be >= 1")


@dataclass(frozen=True)
class LoadingDefaults:
    """Defaults of the loading programmes (spec section 9)."""

    increment: float = 1e-5
    """Axial strain increment of the shear stage [-]."""
    iso_increment: float = 5e-6
    """Volumetric-strain increment per component of the isotropic stage [-]."""
    eps_max: float = 0.2
    """Axial strain eps1 at the end of the shear stage, counted from its start [-]."""
    stress_rtol: float = 1e-5
    """Relative tolerance of stress-controlled components [-], 100 times finer than the 1e-3 of
    p0 to which the backends are compared. At 1e-6 the DEM's drained runs also converge, but
    need ~2 step calls per increment instead of ~1.1 (docs/dem_stepping.md)."""
    max_newton_iterations: int = 30
    """Newton iterations allowed per stress-controlled increment [-]."""


@dataclass(frozen=True)
class FeDefaults:
    """Defaults of the plane-strain biaxial boundary-value problem (``homogenization.bvp``)."""

    width: float = 1.0
    """Specimen width W [m] (the H-model has no length scale: only W/H matters)."""
    height: float = 2.0
    """Specimen height H [m]."""
    elements: tuple[int, int] = (4, 8)
    """Bilinear quadrilaterals across the width and along the height [-]."""
    n_orientations: int = 72
    """Cell orientations per Gauss point [-]."""
    eps_max: float = 0.05
    """Axial strain of the shear stage, counted from its start [-]."""
    increment: float = 1e-3
    """Axial strain of one shear step (top-platen displacement / H) [-]."""
    iso_steps: int = 20
    """Load steps of the isotropic stage [-]."""
    newton_rtol: float = 1e-8
    """Newton converges when the out-of-balance force norm is below this times p0 W [-]."""
    max_newton: int = 25
    """Newton iterations allowed per load step [-]."""
    isotropic_seed: float = 1e-6
    """Homogeneous isotropic strain of the first Newton guess [-]: the touching, force-free
    cells have no stiffness, a small compression closes them."""


@dataclass(frozen=True)
class DemSettings:
    """Numerical settings of the meso-DEM (spec section 10)."""

    density: float = 2650.0
    """Grain density [kg/m^3]; disk mass per unit thickness is density * pi r^2 [kg/m]."""
    dt_factor: float = 0.6
    """Time step as a fraction of sqrt(m / kn) of the lightest grain [-] (quasi-static results
    do not depend on it; with ``damping`` 0.7 it relaxes in fewer substeps than 0.4 / 0.5, and
    keeps the slide tangent of the step equal to the condensed one, which 0.6 / 0.6 and
    0.8 / 0.7 do not; docs/dem_stepping.md)."""
    damping: float = 0.7
    """Cundall local (non-viscous) damping coefficient [-]."""
    strain_per_substep: float = 2.5e-5
    """Largest cell-strain component applied per substep while driving [-]."""
    refined_strain_per_substep: float = 5e-6
    """Strain per substep of an increment that changes the cell's path (see velocity_change),
    and for the rest of an increment once a contact of the cell has opened, closed, started or
    stopped sliding in it (<= strain_per_substep) [-]."""
    closing_strain_per_substep: float = 5e-7
    """Strain per substep for the rest of an increment once a contact of the cell has closed in it,
    capped at refined_strain_per_substep (``closing_rate``) [-]: the free grains a new contact pushes start from rest,
    and while they lag behind the driving a contact that quasi-statically sticks near the
    Coulomb cap slides and loses spring; the loss grows with this rate (docs/dem_stepping.md,
    "Contacts that close again")."""
    rest_strain_per_substep: float = 1e-6
    """Strain per substep, in place of refined_strain_per_substep, of an increment stepped from rest (no
    velocity memory: the database's probes, the DEM's reproducibility in a certificate, the hybrid's escalation;
    ``from_rest``) [-]. Its free grains start from rest while the driven ones move, and lag behind; at 5e-6
    where a fine grain is about to leave its wedge, the lag decided when it left: drained compression of
    benchmarks/cells/large_axial.toml (100 cells, 1e-4 to 10 %) from rest differed from the DEM by 2.1 %
    of the scale, at 2.5e-6 / 1e-6 / 5e-7 / 2e-7 by 0.012 / 0.003 / 0.011 / 0.005 % (docs/dem_stepping.md,
    "Increments from rest")."""
    velocity_change: float = 0.5
    """Largest deviation of the last increment's driven displacements per driving substep from
    the direction of the new increment's, as a fraction of their size, for the increment to
    count as continuing the path: the strain per substep then grows rather than restart from
    refined_strain_per_substep, and the free grains are predicted from their last motion [-]."""
    rate_growth: float = 2.0
    """Largest growth of the strain per substep from one increment to the next [-]."""
    force_tolerance: float = 1e-6
    """Quasi-static criterion: unbalanced force ratio below this value [-]. With the predicted
    free grains a cell arrives near equilibrium, so 1e-6 costs ~10 % more substeps than 1e-5
    and keeps the response smooth enough for stress control to 1e-6 (docs/dem_stepping.md)."""
    max_substeps: int = 200_000
    """Substeps allowed per increment before a cell is reported unconverged [-]."""
    contact_tolerance: float = 1e-9
    """Gap, as a fraction of the mean diameter of the pair, that still counts as a contact [-]."""

    def __post_init__(self) -> None:
        check_positive("density", self.density)
        check_positive("dt_factor", self.dt_factor)
        check_positive("strain_per_substep", self.strain_per_substep)
        check_positive("refined_strain_per_substep", self.refined_strain_per_substep)
        if self.refined_strain_per_substep > self.strain_per_substep:
            raise ValueError(f"refined_strain_per_substep = {self.refined_strain_per_substep:g} exceeds "
                             f"strain_per_substep = {self.strain_per_substep:g}")
        check_positive("closing_strain_per_substep", self.closing_strain_per_substep)
        check_positive("rest_strain_per_substep", self.rest_strain_per_substep)
        check_positive("force_tolerance", self.force_tolerance)
        check_positive("velocity_change", self.velocity_change)
        if not self.rate_growth >= 1.0:
            raise ValueError(f"rate_growth = {self.rate_growth:g} must be >= 1")
        if not (0.0 <= self.damping < 1.0):
            raise ValueError(f"damping = {self.damping:g} is outside [0, 1)")
        if int(self.max_substeps) < 1:
            raise ValueError(f"max_substeps = {self.max_substeps} must be >= 1")
        if not (0.0 <= self.contact_tolerance < 1e-3):
            raise ValueError(f"contact_tolerance = {self.contact_tolerance:g} is outside [0, 1e-3)")

    @property
    def from_rest(self) -> "DemSettings":
        """The settings of an increment stepped from rest: refined_strain_per_substep at most
        rest_strain_per_substep (these settings where they already are)."""
        refined = min(self.refined_strain_per_substep, self.rest_strain_per_substep)
        return self if refined == self.refined_strain_per_substep else replace(self, refined_strain_per_substep=refined)

    @property
    def closing_rate(self) -> float:
        """The strain per substep after a contact closes: closing_strain_per_substep, at most
        refined_strain_per_substep [-] (settings that drive at one fine rate keep it)."""
        return min(self.closing_strain_per_substep, self.refined_strain_per_substep)


@dataclass(frozen=True)
class DatabaseSettings:
    """Options of the learning-database generator ``warp_hcell.generate`` (spec section 11).

    Strains are compression positive; a path length is sqrt(sum d_eps_n^2 + d_eps_t^2) in
    the (eps_n, eps_t) plane of the cell.
    """

    samples: int = 300_000
    """Number of samples (one strain probe of one sampled state each) [-]."""
    chunk_size: int = 5_000
    """Probes computed as one batch; also the unit of resume and of parallel work [-]."""
    precompression: tuple[float, ...] = (0.0, 1e-3, 3e-3, 1e-2, 2e-2, 3e-2)
    """Isotropic strains eps_n = eps_t from which the proportional legs start [-]
    (p ~ 2.2e8 N/m x eps: 1e-3 ~ p0 = 2e5 N/m, 2e-2 to 3e-2 ~ p0 = 5.85e6 N/m)."""
    n_directions: int = 24
    """Leg directions psi_k = 360 k / n_directions [deg] in the (eps_n, eps_t) plane [-]."""
    sample_spacing: float = 5e-3
    """Path length between sampled states, also the exploration increment [-]."""
    leg_refinement: int = 3
    """A leg's first increment is sample_spacing / 2**leg_refinement, then increments double
    up to sample_spacing (finer sampling just after the change of direction) [-]."""
    leg_length: float = 0.45
    """Largest path length of a leg [-] (constant-volume shearing to eps1 = 0.3 moves a
    cell by up to 0.3 sqrt 2)."""
    leg_volumetric: float = 0.08
    """Largest change ``|d(eps_n + eps_t)|`` of the cell's volumetric strain along a leg [-]
    (drained biaxial shear of H-cells to eps1 = 0.2 changes it by up to 0.069: alpha0 = 40 deg,
    p0 = 2e5 N/m; every cell of a biaxial test shares the macroscopic volumetric strain)."""
    probe_min: float = 1e-6
    """Smallest probe magnitude ``|d_eps|`` [-]."""
    probe_max: float = 1e-3
    """Largest probe magnitude ``|d_eps|`` [-]."""
    probe_focus_min: float = 1e-5
    """Smallest magnitude of the focus probes (the ANN's usual increments) [-]."""
    probe_focus_max: float = 1e-4
    """Largest magnitude of the focus probes [-]."""
    probe_focus_fraction: float = 0.5
    """Fraction of the probes drawn in [probe_focus_min, probe_focus_max] [-]."""
    perturbed_fraction: float = 0.25
    """Fraction of the probes whose start state is a sampled equilibrium state with its free
    DOFs displaced at random (the DEM relaxes it during the probe) [-]."""
    zero_probe_fraction: float = 0.3
    """Fraction of the perturbed probes with d_eps = 0 (relaxation alone) [-]."""
    perturbation_min: float = 1e-6
    """Smallest perturbation amplitude, as a fraction of the mean grain diameter D [-]."""
    perturbation_max: float = 5e-4
    """Largest perturbation amplitude / D [-]: half the typical overlap ~1e-3 D at p0 = 2e5 N/m
    (a contact may open), 1/60 of it at p0 = 5.85e6 N/m. Amplitudes are log-uniform in
    [perturbation_min, perturbation_max]; each free DOF moves by amplitude x D x N(0, 1)."""
    stress_free_length: float = 0.02
    """A path stops once it has carried no contact force over this path length [-]."""
    max_overlap: float = 0.15
    """A path stops when an overlap exceeds this fraction of r_i + r_j [-] (p0 = 5.85e6 N/m
    gives ~0.03 on the H-cell)."""
    max_cell_strain: float = 0.5
    """A path stops when ``|eps_n|`` or ``|eps_t|`` summed from its start cell exceeds this [-]."""
    reversal_legs: int = 1
    """Turning branches per proportional leg [-]: each leaves one of the leg's sampled states
    (the turn) in a direction turned back from the leg's (unloading, then loading the other
    way) and runs like a leg (same increments, path length and volumetric limits); 0 = none."""
    reversal_arc: tuple[float, float] = (0.01, 0.2)
    """Range of the leg's path length at the turn [-]; the turn is one of the leg's sampled
    states in it, drawn uniformly (with reversal legs the generator refuses a range holding none; constant-volume shear to eps1 = 5 %
    moves a cell by up to 0.05 sqrt 2 = 0.07)."""
    reversal_negated_fraction: float = 0.5
    """Fraction of the branches whose direction is the leg's negated [-]; the others turn by an
    angle drawn uniformly in [reversal_min_angle_deg, 180] deg, either sense."""
    reversal_min_angle_deg: float = 100.0
    """Smallest turn of the branches that are not negated [deg], in (90, 180]: every branch
    strains back against its leg."""

    def __post_init__(self) -> None:
        if int(self.leg_refinement) < 0:
            raise ValueError(f"leg_refinement = {self.leg_refinement} must be >= 0")
        if int(self.reversal_legs) < 0:
            raise ValueError(f"reversal_legs = {self.reversal_legs} must be >= 0")
        lo, hi = self.reversal_arc
        if not 0.0 < lo <= hi:
            raise ValueError(f"reversal_arc = {self.reversal_arc} must satisfy 0 < low <= high")
        if not 90.0 < self.reversal_min_angle_deg <= 180.0:
            raise ValueError(f"reversal_min_angle_deg = {self.reversal_min_angle_deg:g} must lie in (90, 180]")
        if not 0.0 <= self.reversal_negated_fraction <= 1.0:
            raise ValueError(f"reversal_negated_fraction = {self.reversal_negated_fraction:g} is outside [0, 1]")
        for name in ("samples", "chunk_size", "n_directions"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} = {getattr(self, name)} must be >= 1")
        for name in ("sample_spacing", "leg_length", "leg_volumetric", "probe_min", "probe_focus_min"):
            check_positive(name, getattr(self, name))
        if not self.precompression or min(self.precompression) < 0.0 or not all(map(math.isfinite, self.precompression)):
            raise ValueError(f"precompression = {self.precompression} needs finite strains >= 0")
        for lo, hi in (("probe_min", "probe_max"), ("probe_focus_min", "probe_focus_max")):
            if not getattr(self, lo) <= getattr(self, hi) < 1.0:
                raise ValueError(f"{hi} = {getattr(self, hi):g} must lie in [{lo}, 1)")
        for name in ("probe_focus_fraction", "perturbed_fraction", "zero_probe_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} = {getattr(self, name):g} is outside [0, 1]")
        for name in ("perturbation_min", "stress_free_length", "max_overlap", "max_cell_strain"):
            check_positive(name, getattr(self, name))
        if not self.perturbation_min <= self.perturbation_max < 1.0:
            raise ValueError(f"perturbation_max = {self.perturbation_max:g} must lie in [perturbation_min, 1)")
