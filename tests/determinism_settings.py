"""``make determinism``: the tests marked ``determinism`` under every CPU-feature setting, one pytest each, and
the tests marked ``other_cpus`` once (they compile the meso-ANN's steps for other CPUs and compare the bits).

numpy, OpenBLAS, torch (ATen, MKL, oneDNN), numba and glibc pick their kernels by CPU; these variables
make them pick those of another CPU, so that one machine checks what an AVX2 or an AVX-512
machine would compute (docs/determinism.md). A setting puts every library at one level at once (each
library picks its kernels on its own, so one run checks them all); a setting that fails is run again one
library at a time, so that the log names the library. Settings that need AVX-512 run only where the CPU
has it. The settings run two at a time (each its own process; those that compile numba for another CPU
start first, after the ``other_cpus`` tests, and those whose CPUs these tests compile for start once the tests'
processes for those CPUs have finished, while the tests compare on the host). Prints
one line per setting, in order, then the ``other_cpus`` line and the total time; exit status 1 if any of them
failed.

    python tests/determinism_settings.py [pytest arguments, e.g. -x]
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from other_cpus import COMPILED_SIGNAL, OTHER_CPUS

ROOT = Path(__file__).resolve().parents[1]
NUMPY_AVX2 = "X86_V4 AVX512_ICL AVX512_SPR"
"""numpy's dispatch groups above AVX2 (numpy >= 2.4 names the x86-64 levels X86_V3, X86_V4)."""
NUMPY_BASELINE = "X86_V3 " + NUMPY_AVX2
"""Every numpy dispatch group above its baseline (SSE4.2)."""
GLIBC_NO_FMA = "glibc.cpu.hwcaps=-AVX2_Usable,-FMA_Usable,-FMA"
"""glibc's exp, log, sin, cos, atan2 ... without their AVX2 and FMA variants (as on a CPU without FMA)."""
SETTINGS: list[tuple[dict[str, str], bool]] = [
    ({}, False),
    ({"NPY_DISABLE_CPU_FEATURES": NUMPY_AVX2, "OPENBLAS_CORETYPE": "Haswell", "ATEN_CPU_CAPABILITY": "avx2",
      "MKL_CBWR": "AVX2", "DNNL_MAX_CPU_ISA": "AVX2", "NUMBA_CPU_NAME": "haswell"}, False),
    ({"OPENBLAS_CORETYPE": "SkylakeX", "ATEN_CPU_CAPABILITY": "avx512", "MKL_CBWR": "AVX512",
      "DNNL_MAX_CPU_ISA": "AVX512_CORE"}, True),
    ({"NPY_DISABLE_CPU_FEATURES": NUMPY_BASELINE, "OPENBLAS_CORETYPE": "Sandybridge", "ATEN_CPU_CAPABILITY": "default",
      "MKL_CBWR": "COMPATIBLE", "DNNL_MAX_CPU_ISA": "SSE41", "NUMBA_CPU_NAME": "generic",
      "GLIBC_TUNABLES": GLIBC_NO_FMA}, False),
]
"""(environment variables, needs AVX-512): the host as it is, then every library at its AVX2 level, at its
AVX-512 level, and at its lowest level (numpy's SSE4.2 baseline, OpenBLAS's and glibc's kernels for a CPU
without FMA, numba's generic x86-64). The AVX-512 setting leaves numba at the host's CPU: it runs only on a host
with AVX-512, for which numba compiles AVX-512 code already (and loads the first setting's kernels instead of
compiling them for a named AVX-512 CPU, about 40 s of CPU). The ``other_cpus`` tests compile the meso-ANN's steps
for numba's haswell and generic CPUs, the AVX2 and the last setting's: those two settings then load them from
numba's cache instead of compiling them a second time."""


def has_avx512() -> bool:
    """Whether this CPU has AVX-512 F (Linux: /proc/cpuinfo; elsewhere assumed not)."""
    try:
        return " avx512f " in f" {Path('/proc/cpuinfo').read_text()} ".replace("\n", " ")
    except OSError:
        return False


def marked_files(marker: str = "determinism") -> list[str]:
    """The test files that hold tests marked ``marker`` (collecting only these keeps each run short)."""
    return sorted(str(p.relative_to(ROOT)) for p in (ROOT / "tests").glob("test_*.py")
                  if f"pytest.mark.{marker}" in p.read_text())


OTHER_CPU_NAMES = {variables["NUMBA_CPU_NAME"] for variables in OTHER_CPUS.values()}
"""The CPUs numba compiles for in the ``other_cpus`` tests (``tests/other_cpus.py``)."""

WORKERS = 2
"""Settings run at once (after the first, which fills Warp's and numba's caches alone): the CI machine's cores."""


def start_order(settings: list[dict[str, str]], compiled_elsewhere: set[str]) -> list[int]:
    """Indices of ``settings`` after the first, in the order they start: first those that compile numba for a
    CPU that no earlier setting names and ``compiled_elsewhere`` (the CPUs the ``other_cpus`` tests compile
    for) does not hold (several times the others' time), so that no long one is left alone at the end; last
    those whose CPU is in ``compiled_elsewhere``, so that they find its kernels in numba's cache."""
    seen = {settings[0].get("NUMBA_CPU_NAME")} | compiled_elsewhere
    rank = []
    for variables in settings[1:]:
        cpu = variables.get("NUMBA_CPU_NAME")
        rank.append(2 if cpu in compiled_elsewhere else 0 if cpu not in seen else 1)
        seen.add(cpu)
    return sorted(range(1, len(settings)), key=lambda index: rank[index - 1])


def run_setting(variables: dict[str, str], argv: list[str], files: list[str],
                marker: str = "determinism") -> tuple[subprocess.CompletedProcess, float]:
    """One pytest of the tests marked ``marker`` under ``variables``: (its result, its wall time [s])."""
    t0 = time.perf_counter()
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", marker,
                             *argv, *files], cwd=ROOT, env={**os.environ, **variables}, capture_output=True, text=True)
    return result, time.perf_counter() - t0


def label_of(variables: dict[str, str]) -> str:
    """The setting as the log names it."""
    return " ".join(f"{k}={v!r}" for k, v in variables.items()) or "host CPU as it is"


def report(label: str, result: subprocess.CompletedProcess, seconds: float) -> None:
    """One line for a setting's run, then the tail of its output where it failed."""
    summary = (result.stdout.strip().splitlines() or ["(no output)"])[-1]
    print(f"{'ok    ' if result.returncode == 0 else 'FAILED'} {seconds:5.0f} s  {label}: {summary}", flush=True)
    if result.returncode != 0:
        print(result.stdout[-4000:] + result.stderr[-2000:], flush=True)


def main(argv: list[str]) -> int:
    avx512 = has_avx512()
    files = marked_files()
    failed, start = [], time.perf_counter()
    runnable = []
    for variables, needs_avx512 in SETTINGS:
        if needs_avx512 and not avx512:
            print(f"skipped (no AVX-512): {label_of(variables)}", flush=True)
        else:
            runnable.append(variables)
    first = run_setting(runnable[0], argv, files)
    with tempfile.TemporaryDirectory(prefix="other_cpus_") as signals, ThreadPoolExecutor(max_workers=WORKERS) as pool:
        compiled = Path(signals) / "compiled"
        other_cpus = pool.submit(run_setting, {COMPILED_SIGNAL: str(compiled)}, argv, marked_files("other_cpus"),
                                 "other_cpus")

        def setting(variables):
            if variables.get("NUMBA_CPU_NAME") in OTHER_CPU_NAMES:
                # their numba kernels: compiled by the other_cpus tests' processes, then loaded from the cache (the
                # tests' own comparisons on the host CPU go on beside)
                while not (compiled.exists() or other_cpus.done()):
                    time.sleep(0.2)
            return run_setting(variables, argv, files)

        futures = {index: pool.submit(setting, runnable[index])
                   for index in start_order(runnable, OTHER_CPU_NAMES)}
        labelled = [(label_of(variables), futures[index] if index else None, variables)
                    for index, variables in enumerate(runnable)]
        for label, future, variables in [*labelled, ("tests marked other_cpus, host CPU", other_cpus, {})]:
            result, seconds = future.result() if future else first
            report(label, result, seconds)
            if result.returncode != 0:
                failed.append(label)
                if len(variables) > 1:  # which library: each of the setting's variables alone
                    print("  the same tests with one library at this level at a time:", flush=True)
                    for name, value in variables.items():
                        report(f"  {name}={value!r}", *run_setting({name: value}, argv, files))
    print(f"determinism: {len(failed)} of the settings failed in {time.perf_counter() - start:.0f} s"
          + (": " + "; ".join(failed) if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
