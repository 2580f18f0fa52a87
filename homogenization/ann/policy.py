"""Whether a meso-ANN model may be used, and where a run leaves what its certificate covers.

``certificate_problem`` is one line saying why a model may not be used (uncertified, failed,
certified for another ``.pt``, for another surrogate, or below the minimum certificate,
``homogenization.ann.envelope.MINIMUM``), None for a model that passed; the commands refuse such a
model unless ``--uncertified-ok`` (``homogenization.cli.options.refuse_uncertified``).
``CertificatePolicy`` holds a loaded model's certificate beside its cell (``homogenization.ann.cell``):
the problem, the envelope and the exits of a run from it (docs/certificate.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

from homogenization.ann import default_model_path, envelope
from homogenization.ann.escalation import RELEASE_RULES
from homogenization.ann.records import Certificate, certificate_of
from homogenization.material.orientation import cell_kinematics, kinematics_of
from warp_hcell.core.dimension import dimension
from warp_hcell.core.provenance import file_sha256
from warp_hcell.mesostructures.files import from_description
from warp_hcell.mesostructures.mesostructure import Mesostructure


def default_escalation(metadata: dict[str, Any]) -> bool:
    """Whether a hybrid of the model with JSON ``metadata`` hands the cells with a released grain to the DEM
    when nobody says: for a cell with fine grains (``homogenization.ann.envelope.has_fine_grains``),
    where it was measured to follow the DEM closer (docs/ann.md, "Released grains"), not for the plain cell."""
    return envelope.has_fine_grains(from_description(metadata["mesostructure"]))


def certificate_problem(metadata: dict[str, Any], path: Path, corrections: int = 0,
                        tolerance: float | None = None, escalation: bool | None = None,
                        rule: str | None = None) -> str | None:
    """Why model ``path`` (JSON ``metadata``) may not be used, in one line, or None if its
    certificate was measured on this very ``.pt`` (same sha256) and this very surrogate (the
    network with ``corrections`` equilibrium corrections at force ratio ``tolerance`` [-], the
    resolved one; 0: the network alone, ``envelope.equilibrium_settings``), is within its target
    and meets the minimum certificate (``envelope.MINIMUM``), read from its recorded settings, not from
    its ``passed`` flag. ``escalation``: whether the hybrid hands the cells with a released grain to the DEM
    (``AnnCell``'s ``dem_escalation``; None: ``default_escalation``); a certificate of the hybrid records
    whether it did (``envelope.escalation_of``) and by which rule (``rule``, one of ``escalation.RELEASE_RULES``;
    None: any of them, the cell running the one its certificate records)."""
    cert = certificate_of(metadata)
    if cert is None:
        return (f"{path}: the model is uncertified (certify it: python -m homogenization.certify "
                f"--model {path} --write)")
    if cert.model_sha256 != file_sha256(path):
        return f"{path}: its certificate was measured on another model file (sha256 differs); certify it again"
    run = (int(corrections), float(tolerance)) if corrections else (0, None)
    measured = envelope.equilibrium_settings(cert)
    if run != measured:
        return (f"{path}: its certificate measured {_surrogate(*measured)}, not {_surrogate(*run)} "
                f"(run it with {_flags(*measured)}, or certify it with {_flags(*run)})")
    escalation = default_escalation(metadata) if escalation is None else bool(escalation)
    if corrections and escalation != envelope.escalation_of(cert):
        said = {True: "with", False: "without"}
        return (f"{path}: its certificate measured the hybrid {said[envelope.escalation_of(cert)]} the DEM's "
                f"increment in cells with a released grain, this run is {said[escalation]} it; certify the "
                f"model again")
    recorded = envelope.escalation_rule_of(cert)
    if corrections and escalation and (recorded not in RELEASE_RULES or (rule is not None and recorded != rule)):
        return (f"{path}: its certificate measured the hybrid handing cells to the DEM by another rule "
                f"({recorded or 'a grain that moved and overlaps nothing'}) than this run's "
                f"({rule or RELEASE_RULES[0]}); certify the model again")
    result = envelope.verdict(cert)
    if result == "failed" or (result == "passed" and not cert.passed):
        return (f"{path}: the model failed its certificate (worst {100 * float(cert.worst):.3g} % of the scale "
                f"in test {cert.worst_test!r}, target {100 * float(cert.target):.3g} %)")
    if result == "weak":
        return (f"{path}: its certificate is below the minimum certificate "
                f"({'; '.join(envelope.shortfalls(cert, envelope.dimension_of(cert)))}); certify it with the defaults")
    return None


def _surrogate(corrections: int, tolerance: float | None) -> str:
    """The surrogate of (K, tolerance) in words."""
    return (f"the network with {corrections} equilibrium corrections at tolerance {tolerance:g}" if corrections
            else "the network alone")


def _flags(corrections: int, tolerance: float | None) -> str:
    """The command-line flags of the surrogate (K, tolerance)."""
    return (f"--equilibrium-corrections {corrections} --equilibrium-tolerance {tolerance:g}" if corrections
            else "no --equilibrium-corrections")


def model_record(path: Path | None, metadata: dict[str, Any] | None = None, corrections: int = 0,
                 tolerance: float | None = None, escalation: bool | None = None) -> dict[str, Any]:
    """What a run file records of ANN model ``path`` (None: the installed planar model): ``path``
    (resolved), ``sha256`` of the ``.pt``, ``certificate_worst`` (the certificate's worst figure,
    a fraction of the scale; None uncertified), ``certified`` (``certificate_problem`` is None)
    and ``certificate_problem`` (its line, or None) for runs with ``corrections`` equilibrium
    corrections at ``tolerance``, with or without the DEM ``escalation``. ``metadata``: the model's
    JSON, read from beside ``path`` when None."""
    path = (default_model_path() if path is None else Path(path)).resolve()
    if metadata is None:
        from training.checkpoint import read_metadata  # noqa: PLC0415

        metadata = read_metadata(path)
    problem = certificate_problem(metadata, path, corrections, tolerance, escalation)
    cert = certificate_of(metadata)
    return {"path": str(path), "sha256": file_sha256(path),
            "certificate_worst": None if cert is None else cert.worst,
            "certified": problem is None, "certificate_problem": problem}


class CertificatePolicy:
    """A loaded model's certificate and what it allows, beside the cell that steps the model.

    Args:
        metadata: the model's JSON.
        path: the model file (``.pt``).
        dim: the model's cell dimension (its stress unit).
        corrections, tolerance, escalation, rule: the surrogate the cell runs (``certificate_problem``).

    Attributes:
        certificate: the JSON's certificate (None: uncertified).
        problem: ``certificate_problem``'s line for this surrogate, or None; ``check_kinematics`` may set it.
    """

    def __init__(self, metadata: dict[str, Any], path: Path, dim: int, corrections: int, tolerance: float | None,
                 escalation: bool, rule: str | None = None) -> None:
        self.path = path
        self.dim = int(dim)
        self.certificate: Certificate | None = certificate_of(metadata)
        self.problem: str | None = certificate_problem(metadata, path, corrections, tolerance, escalation, rule)

    @property
    def envelope(self) -> dict[str, Any] | None:
        """The certificate's envelope (``homogenization.ann.envelope.envelope_of``); None uncertified."""
        return None if self.certificate is None else envelope.envelope_of(self.certificate)

    def envelope_exits(self, programme: Sequence[Any], meso: Mesostructure) -> list[str] | None:
        """Where ``programme`` (``homogenization.element_test.programme``) run on cells of ``meso`` leaves the
        certificate's envelope, one phrase each (``envelope.outside``, stresses in the unit of the model's
        dimension; empty: inside); None for an uncertified model (no envelope)."""
        if self.envelope is None:
            return None
        return envelope.outside(self.envelope, tuple(programme), mesostructure=meso.name,
                                cell_parameters=meso.parameters, unit=dimension(self.dim).stress_unit)

    @property
    def certified_kinematics(self) -> str:
        """The kinematics (``orientation.KINEMATICS``) of the cells of the certificate's tests, read from the
        cell parameters it recorded (``orientation.kinematics_of``; a certificate that records none: "projected")."""
        return kinematics_of(self.envelope["cell_parameters"] if self.envelope is not None else {})

    def check_kinematics(self, meso: Mesostructure) -> None:
        """Set ``problem`` (if None) where the spatial cells of ``meso`` are driven with other kinematics
        (``orientation.cell_kinematics``) than those of the certificate's tests (``certified_kinematics``)."""
        if meso.dim != 3 or self.problem is not None:
            return
        kinematics, certified = cell_kinematics(meso), self.certified_kinematics
        if kinematics != certified:
            self.problem = (f"{self.path}: its certificate drove the cells with the {certified} "
                            f"kinematics, {meso.name!r} declares the {kinematics} kinematics")

    def standing(self) -> str:
        """The model's standing in a few words (a diagnosis's): not certified and why, or its worst figure."""
        if self.problem is not None:
            return f"model not certified ({self.problem.split(': ', 1)[-1]})"
        return f"model certified (worst {100 * float(self.certificate.worst):.3g} %)"
