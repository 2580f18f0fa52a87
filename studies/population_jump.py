"""python studies/population_jump.py

The calibration's stress control where the drained response jumps across its target
(``homogenization.element_test.solver.POPULATION``): per case, the forward model's fallbacks, jumps taken
and CPU time with plain Newton (the policy without its safeguards), with the policy as shipped and with the
jump located to 1e-6 of the increment (the reference), at 30 and 15 Newton trials, and each curve's largest
distance to the reference as a fraction of its channel's scale. Cases: the drained biaxial test of truth 3
of ``benchmarks/bench_calibrate_truths.py`` (phi_g 42, alpha0 80, p0 3e4 N/m; 32 sets about the truth,
seeded; one controlled stress) and Dobrany sand's drained 50 kPa test at the void-ratio optimum of
docs/studies/calibration_dobrany_critical_state.md (with the critical-state rule; two controlled stresses).
Prints and writes ``studies/results/population_jump.txt``.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from homogenization.calibration import forward
from homogenization.calibration.data import Measurement
from homogenization.calibration.forward import ForwardSettings
from homogenization.calibration.synthetic import synthetic_test
from homogenization.element_test import solver
from homogenization.material.critical_state import DEFAULTS

OUT = Path(__file__).resolve().parent / "results" / "population_jump.txt"
POLICIES = {"plain Newton": replace(solver.POPULATION, bracket=False, segment=False),
            "shipped": solver.POPULATION,
            "reference": replace(solver.POPULATION, jump_width=1e-6)}


def truth3() -> tuple[Measurement, dict[str, np.ndarray], ForwardSettings]:
    eps1 = np.linspace(0.02 / 25, 0.02, 25)
    source = ForwardSettings(n_orientations=72, increment=1e-4, iso_increment=1e-4, stress_rtol=1e-5)
    test, _ = synthetic_test("drained", 3e4, eps1, ("q", "eps_v"), {"phi_g": 42.0, "alpha0": 80.0}, source, 0.02,
                             np.random.default_rng(20))
    rng = np.random.default_rng(1)
    return test, {"phi_g": rng.uniform(38, 45, 32), "alpha0": rng.uniform(78.5, 81.5, 32)}, ForwardSettings()


def dobrany50() -> tuple[Measurement, dict[str, np.ndarray], ForwardSettings]:
    test = Measurement("cid_50kpa", Path("cid_50kpa.csv"), True, 5e4, np.linspace(0.01, 0.25, 25), {}, dim=3,
                       void_ratio=0.524)
    sets = {"phi_g": np.array([37.5]), "kn": np.array([10 ** 7.427]), "kt_over_kn": np.array([1.49]),
            "e_min": np.array([0.4512]), "e_max": np.array([0.70711666666667]), "alpha_c": np.array([53.13]),
            "renewal_rate": np.array([10 ** 1.102])}
    return test, sets, ForwardSettings(increment=2e-3, iso_increment=1e-3, stress_rtol=1e-5, critical_state=DEFAULTS[3])


def main() -> None:
    load = " / ".join(Path("/proc/loadavg").read_text().split()[:3])
    lines = [f"population stress control at a jump; load average {load}"]
    for label, case in (("truth 3 drained biaxial, 32 sets, 36 orientations", truth3),
                        ("Dobrany 50 kPa drained triaxial with the rule, 1 set, Lebedev 11 x 4", dobrany50)):
        test, sets, settings = case()
        lines += ["", label, "policy        trials  fallbacks  jumps  CPU [s]  max|dq|/scale  max|deps_v|/scale"]
        runs = {}
        for name, policy in POLICIES.items():
            for trials in (30, 15):
                forward.POPULATION = policy
                start = time.process_time()
                runs[name, trials] = (forward.simulate(test, sets, replace(settings, max_newton=trials if name !=
                                                                             "reference" else 80)),
                                      time.process_time() - start)
        forward.POPULATION = solver.POPULATION
        ref = runs["reference", 30][0]
        for (name, trials), (c, cpu) in runs.items():
            if name == "reference" and trials == 15:
                continue
            dq, dv = (np.nanmax(np.abs(c.channel(k) - ref.channel(k))) / np.nanmax(np.abs(ref.channel(k)))
                      for k in ("q", "eps_v"))
            lines.append(f"{name:<13} {trials if name != 'reference' else 80:<7} {int(c.n_fallback.sum()):<10} "
                         f"{int(c.n_jump.sum()):<6} {cpu:<8.3f} {dq:<14.2e} {dv:.2e}")
        print("\n".join(lines[-len(runs) - 1:]), flush=True)
    OUT.write_text("\n".join(lines) + "\n")
    print(f"-> {OUT}")


if __name__ == "__main__":
    main()
