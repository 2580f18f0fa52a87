"""Sampler diagnostics of hmodel calibrate chains, side by side (docs/studies/calibration_sampler_moves.md).

    python studies/calibration_sampler_moves.py --tag TAG NAME=RUN_FOLDER[:STEPS] ...

For each chain (its first STEPS steps; default all) the command's own diagnostics, recomputed on that prefix with
its burn-in fraction (0.5) and stuck-walker rule (``report.retained_chain``): acceptance over all steps, over the
first 8 and over the retained half, the walkers stuck, tau and effective samples per parameter, retained steps per
largest tau, and the steps the command would ask for (``diagnostics.steps_needed``); also the retained walkers'
spread per parameter (sd in sampled coordinates) and their log posterior's median and best; the median and best
walker's log posterior every 10 steps (all walkers: is the ensemble still climbing?). Writes
studies/results/calibration_sampler_moves_TAG.{json,txt}.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from homogenization.calibration import diagnostics
from homogenization.calibration.report import retained_chain

RESULTS = Path(__file__).resolve().parent / "results"
BURN = 0.5


class Prefix:
    """The first ``steps`` steps of an emcee HDF5 chain, read as ``report.retained_chain`` reads a sampler."""

    def __init__(self, chain: np.ndarray, log_prob: np.ndarray):
        self.chain, self.log_prob = chain, log_prob
        self.backend = SimpleNamespace(iteration=chain.shape[0])

    def get_chain(self, discard: int = 0) -> np.ndarray:
        return self.chain[discard:]

    def get_log_prob(self, discard: int = 0) -> np.ndarray:
        return self.log_prob[discard:]


def moved_fraction(chain: np.ndarray) -> np.ndarray:
    """Per step (from the second), the fraction of walkers whose position changed: the acceptance of that step."""
    return np.mean(np.any(chain[1:] != chain[:-1], axis=2), axis=1)


def summary(folder: Path, steps: int | None) -> dict:
    import h5py  # noqa: PLC0415

    with h5py.File(folder / "chain.h5", "r") as fh:
        chain = np.array(fh["mcmc"]["chain"])
        log_prob = np.array(fh["mcmc"]["log_prob"])
        accepted = np.array(fh["mcmc"]["accepted"])
        config = json.loads(fh.attrs["calibration_config"])
        n = int(fh["mcmc"].attrs["iteration"])  # steps written
    steps = n if steps is None else min(steps, n)
    chain, log_prob = chain[:steps], log_prob[:steps]
    names = config["params"]
    kept, lp, discard, stuck = retained_chain(Prefix(chain, log_prob), BURN)
    diag = diagnostics.chain_diagnostics(kept, names)
    moved = moved_fraction(chain)
    return {
        "folder": str(folder), "moves": config.get("moves", "stretch"), "steps": steps, "walkers": chain.shape[1],
        "acceptance_all_steps_final": float(np.mean(accepted) / n) if steps == n else None,
        "acceptance": float(np.mean(moved[: steps - 1])),
        "acceptance_first_8": float(np.mean(moved[:7])),
        "acceptance_retained": float(np.mean(moved[discard:])),
        "stuck_walkers_left_out": stuck, "discarded": discard,
        "tau_steps": diag["tau_steps"], "effective_samples": diag["effective_samples"],
        "steps_per_tau": diag["steps_per_tau"], "steps_needed": diagnostics.steps_needed(diag, steps, BURN),
        "walkers_that_never_moved": max(diag["walkers_that_never_moved"].values()),
        "spread_sd": dict(zip(names, np.std(kept.reshape(-1, kept.shape[2]), axis=0).tolist())),
        "log_prob_median": float(np.median(lp)), "log_prob_best": float(np.max(lp)),
        "moved_per_step": moved.tolist(),
        "log_prob_median_per_step": np.median(log_prob, axis=1).tolist(),
        "log_prob_best_per_step": np.max(log_prob, axis=1).tolist(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tag", required=True)
    parser.add_argument("runs", nargs="+", metavar="NAME=FOLDER[:STEPS]")
    args = parser.parse_args(argv)
    out, lines = {}, []
    for item in args.runs:
        name, rest = item.split("=", 1)
        folder, _, steps = rest.partition(":")
        s = summary(Path(folder), int(steps) if steps else None)
        out[name] = s
        taus = [t for t in s["tau_steps"].values() if t is not None]
        ess = [e for e in s["effective_samples"].values() if e is not None]
        lines.append(f"{name}: {s['moves']}, {s['steps']} steps x {s['walkers']} walkers; acceptance {s['acceptance']:.3f} "
                     f"(first 8 steps {s['acceptance_first_8']:.3f}, retained {s['acceptance_retained']:.3f}); "
                     f"stuck {s['stuck_walkers_left_out']}; never moved in the retained half "
                     f"{s['walkers_that_never_moved']}; tau {min(taus):.1f}-{max(taus):.1f} steps; effective samples "
                     f"{min(ess):.0f}-{max(ess):.0f}; {s['steps_per_tau']:.1f} tau retained; steps needed "
                     f"{s['steps_needed']}; log posterior median {s['log_prob_median']:.1f}, best {s['log_prob_best']:.1f}")
        lines.append("  tau per parameter: " + ", ".join(f"{k} {v:.1f}" for k, v in s["tau_steps"].items()
                                                          if v is not None))
        marks = [0, *range(9, s["steps"], 10)]
        lines.append("  log posterior median / best at steps " + ", ".join(
            f"{k + 1}: {s['log_prob_median_per_step'][k]:.0f} / {s['log_prob_best_per_step'][k]:.0f}" for k in marks))
        lines.append("  retained sd per parameter: " + ", ".join(f"{k} {v:.3g}" for k, v in s["spread_sd"].items()))
    text = "\n".join(lines)
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"calibration_sampler_moves_{args.tag}.json").write_text(json.dumps(out, indent=1))
    (RESULTS / f"calibration_sampler_moves_{args.tag}.txt").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
