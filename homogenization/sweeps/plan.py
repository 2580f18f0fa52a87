"""The cases of a sweep (``hmodel sweep``, ``homogenization.cli.sweep``): what runs, planned before anything runs.

``plan`` builds and validates every mesostructure of the Cartesian product --mesostructure x
--alpha0 x --p0 x --backend, skips the combinations a backend refuses
(``homogenization.backends.mesostructure_refusal``), picks each ann case's model
(``ModelTable``; an ann case records where it leaves its model's certificate envelope,
``ann_model.outside_envelope``) and gives every case its folder and the run parameters whose equality decides
whether a stored run is that case. Bad input is a ``UserError`` (one line) before any case runs.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from homogenization.element_test import programme as programmes
from homogenization.backends import backend_class, mesostructure_refusal
from warp_hcell.core.errors import UserError
from warp_hcell.core.parameters import CellDefaults, ContactLaw
from warp_hcell.mesostructures.builders import MesostructureSource, mesostructure_list_arg
from warp_hcell.mesostructures.files import describe, description_sha256
from warp_hcell.mesostructures.mesostructure import Mesostructure, MesostructureError


@dataclass(frozen=True)
class ModelChoice:
    """One --model item: a model file, for one mesostructure (``key``, its text) or any (None)."""

    key: str | None
    path: Path


def _topology(pairs: Any, driven: Any) -> tuple[str, str]:
    """A cell's grains as a network sees them (its pairs and driven dofs), comparable between a model's schema and a
    mesostructure."""
    return json.dumps(np.asarray(pairs).tolist()), json.dumps(np.asarray(driven).tolist())


class ModelTable:
    """The --model items, checked: which model file runs which ann case.

    Raises (constructor and ``for_case``):
        UserError: an unreadable model, a key that is not one of --mesostructure, a fines
            mesostructure without a model, a model of another mesostructure (one line).
    """

    def __init__(self, choices: Sequence[ModelChoice] | None, sources: Sequence[MesostructureSource]) -> None:
        from training.checkpoint import CheckpointError, read_metadata  # noqa: PLC0415 torch only for ann

        self.sha256: dict[Path, str] = {}
        self._cells: dict[Path, tuple[str, Any]] = {}  # a model's cell: (its name, its grains' pairs and driven dofs)
        self.keyed: dict[str, Path] = {}
        self.bare: list[Path] = []
        self._records: dict[Path | None, dict[str, Any]] = {}
        self._envelopes: dict[Path | None, dict[str, Any] | None] = {}
        texts = {source.text: source for source in sources}
        for choice in choices or ():
            if not choice.path.is_file():
                raise UserError(f"--model {choice.path}: no such model file")
            try:
                metadata = read_metadata(choice.path)
            except CheckpointError as exc:
                raise UserError(str(exc)) from None
            self.sha256[choice.path] = metadata["mesostructure_sha256"]
            self._cells[choice.path] = (json.loads(metadata["mesostructure"])["name"],
                                        _topology(metadata["schema"]["pairs"], metadata["schema"]["driven"]))
            if choice.key is None:
                self.bare.append(choice.path)
                continue
            key = self._source_text(choice.key, texts)
            if key in self.keyed and self.keyed[key] != choice.path:
                raise UserError(f"--model gives two models for {choice.key}")
            self.keyed[key] = choice.path

    @staticmethod
    def _source_text(key: str, texts: Mapping[str, MesostructureSource]) -> str:
        if key in texts:
            return key
        for text, source in texts.items():
            if source.kind is None and Path(key).resolve() == Path(text).resolve():
                return text
        raise UserError(f"--model {key}=...: {key} is not one of --mesostructure ({', '.join(texts)})")

    def for_case(self, source: MesostructureSource, meso: Any, plain: bool) -> Path | None:
        """The model file of an ann case (None: the installed model; plain H-cell only)."""
        sha = description_sha256(describe(meso))
        path = self.keyed.get(source.text)
        if path is None:
            path = next((p for p in self.bare if self.sha256[p] == sha), None)
        if path is None and plain:
            path = self.bare[0] if len(self.bare) == 1 else None
            name, topology = self._cells.get(path, (None, None))
            if path is not None and topology != _topology(meso.pairs, meso.driven):
                raise UserError(f"--model {path} is a model of {name}, whose grains differ from those of "
                                f"{source.text}: give its model with --model {source.text}=PATH, or none")
            return path
        if path is None:
            raise UserError(f"no ANN model for mesostructure {source.text} ({meso.name}, sha256 {sha[:12]}); "
                            f"pass --model {source.text}=PATH with a model trained on it")
        if not plain and self.sha256[path] != sha:
            raise UserError(f"--model {path} was trained on mesostructure {self.sha256[path][:12]}, not on "
                            f"{source.text} ({sha[:12]}; the hash covers the spec text: generate with the same)")
        return path

    def record(self, path: Path | None) -> dict[str, Any]:
        """What the run files of an ann case record of its model ``path`` (None: the installed
        model): ``homogenization.ann.policy.model_record`` (sha256, certificate worst,
        certified, the problem), computed once per file."""
        from homogenization.ann.policy import model_record  # noqa: PLC0415 torch only for ann

        if path not in self._records:
            self._records[path] = model_record(path)
        return self._records[path]

    def outside_envelope(self, path: Path | None, programme: Any, meso: Mesostructure) -> list[str] | None:
        """Where ``programme`` on cells of ``meso`` leaves the certificate envelope of model ``path``
        (None: the installed model): ``homogenization.ann.envelope.outside``'s phrases, empty inside;
        None for a model without a certificate."""
        from homogenization.ann import default_model_path  # noqa: PLC0415 torch only for ann
        from homogenization.ann.envelope import envelope_of, outside  # noqa: PLC0415
        from homogenization.ann.records import certificate_of  # noqa: PLC0415
        from training.checkpoint import read_metadata  # noqa: PLC0415

        if path not in self._envelopes:
            cert = certificate_of(read_metadata(default_model_path() if path is None else path))
            self._envelopes[path] = None if cert is None else envelope_of(cert)
        envelope = self._envelopes[path]
        if envelope is None:
            return None
        return outside(envelope, programme, mesostructure=meso.name, cell_parameters=meso.parameters)


@dataclass(frozen=True)
class Case:
    """One run of the sweep; everything a worker needs (picklable, plain values).

    Attributes:
        source: mesostructure text (spec or file).
        backend: backend name.
        alpha0: opening angle [deg] passed to the driver (NaN for a file that is not a plain H-cell).
        p0: confining pressure [N/m].
        folder: case folder.
        parameters: the run parameters written to run.h5 (JSON-compatible); their equality
            decides whether a stored run is this case.
        options: backend options that do not change results (threads).
    """

    source: str
    backend: str
    alpha0: float
    p0: float
    folder: str
    parameters: dict[str, Any]
    options: dict[str, Any]


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._=+-]+", "_", text).strip("_") or "case"


def plan(args: Any) -> tuple[list[Case], list[str]]:
    """Cases of the product (mesostructures built and validated) and the skipped combinations.

    Args:
        args: the sweep's options (``homogenization.cli.sweep.build_parser``): mesostructure,
            alpha0, p0, backend, model, erode_at, eps_max, increment, iso_increment,
            orientations, drained, stress_rtol, device, threads.

    Raises:
        UserError: a mesostructure that does not build, an option no case takes (one line).
    """
    sources: list[MesostructureSource] = args.mesostructure or mesostructure_list_arg("hcell")
    sources = list({s.text: s for s in sources}.values())
    law = ContactLaw()
    if args.model is not None and "ann" not in args.backend:
        raise UserError("--model applies to --backend ann only")
    models = ModelTable(args.model, sources) if "ann" in args.backend else None
    cases: list[Case] = []
    skipped: list[str] = []
    for source in sources:
        alphas = args.alpha0 if source.takes_alpha0 else [source.fixed_alpha0]
        for alpha0 in alphas:
            try:
                meso = source.build(alpha0)
            except MesostructureError as exc:
                raise UserError(str(exc)) from None
            if meso.dim != 2:
                raise UserError(f"--mesostructure {source.text}: a 3D cell; a sweep runs biaxial tests of planar cells "
                                f"(hmodel triaxial runs 3D ones)")
            plain = _closed_form_cell(meso)
            erodible = bool(np.any(~meso.driven.any(axis=1)))
            for p0 in args.p0:
                for backend in args.backend:
                    refusal = mesostructure_refusal(backend, meso)
                    if refusal is not None:
                        skipped.append(f"{backend} x {source.text}: {refusal}")
                        continue
                    erode_at = args.erode_at if erodible else None
                    if erode_at is not None and backend != "dem":
                        raise UserError(f"--erode-at needs --backend dem; {backend} cannot remove grains of {source.text}")
                    if erode_at is not None and erode_at >= args.eps_max:
                        raise UserError(f"--erode-at {erode_at:g} must be below --eps-max {args.eps_max:g}")
                    case_alpha0 = plain[0] if plain is not None else (float("nan") if alpha0 is None else float(alpha0))
                    radius = plain[1] if plain is not None else CellDefaults.radius
                    model = models.for_case(source, meso, plain is not None) if backend == "ann" else None
                    ann = {}
                    if backend == "ann":
                        programme = programmes.biaxial(p0, args.eps_max, args.increment, drained=args.drained)
                        ann = {"ann_model": {**models.record(model),
                                             "outside_envelope": models.outside_envelope(model, programme, meso)}}
                    parameters = {
                        "backend": backend,
                        "backend_options": ({"device": args.device} if backend in ("dem", "ann") else {})
                        | ({"model": str(model)} if model is not None else {}),
                        "contact_law": asdict(law), "radius": radius,
                        "alpha0_deg": None if math.isnan(case_alpha0) else case_alpha0, "p0": p0,
                        "eps_max": args.eps_max, "increment": args.increment, "iso_increment": args.iso_increment,
                        "n_orientations": args.orientations, "fabric_anisotropy": 0.0, "fabric_direction_deg": 0.0,
                        "drained": args.drained, "stress_rtol": args.stress_rtol,
                        "mesostructure": source.text, "mesostructure_name": meso.name,
                        "mesostructure_file": source.text if source.kind is None else None,
                        "mesostructure_sha256": description_sha256(describe(meso)),
                        "n_grains": meso.n_grains, "erode_at": erode_at,
                        "eroded_grains": ([int(g) + 1 for g in np.flatnonzero(~meso.driven.any(axis=1))]
                                          if erode_at is not None else None),
                        **ann,
                    }
                    name = f"{source.label}__a{case_alpha0:g}__p{p0:g}__{backend}"
                    options = {"threads": args.threads} if backend == "dem" else {}
                    cases.append(Case(source.text, backend, case_alpha0, p0, _slug(name), parameters, options))
    if not cases:
        raise UserError("no case to run: " + "; ".join(skipped))
    if args.erode_at is not None and all(case.parameters["erode_at"] is None for case in cases):
        raise UserError(f"--erode-at {args.erode_at:g}: no case's cell has grains free along every axis (fines) "
                        f"to remove")
    _unique_folders(cases)
    return cases, skipped


def _closed_form_cell(meso: Mesostructure) -> tuple[float, float] | None:
    """(alpha0 [deg], grain radius [m]) of a cell the analytical backend models, else None."""
    if mesostructure_refusal("analytical", meso) is not None:
        return None
    return backend_class("analytical").check_mesostructure(meso), float(meso.radius[0])


def _unique_folders(cases: list[Case]) -> None:
    """Give cases that share a folder name a hash of their parameters (in place)."""
    seen: dict[str, int] = {}
    for case in cases:
        seen[case.folder] = seen.get(case.folder, 0) + 1
    for k, case in enumerate(cases):
        if seen[case.folder] > 1:
            digest = hashlib.sha1(json.dumps(case.parameters, sort_keys=True).encode()).hexdigest()[:8]
            cases[k] = dataclasses.replace(case, folder=f"{case.folder}__{digest}")

