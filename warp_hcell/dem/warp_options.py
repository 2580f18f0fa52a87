"""Warp's compile options of every DEM module and kernel, in one place.

The DEM promises the same bits on any x86-64 CPU (docs/determinism.md). Warp compiles CPU
kernels for the host by default (``-march=native``) and lets LLVM contract ``a * b + c`` into
one fused multiply-add (``fuse_fp``), which rounds once instead of twice, where the target has
FMA. Pinned here instead:

- ``cpu_compiler_flags``: no ``-march``, so LLVM generates code for the generic x86-64 target,
  the same machine code on every CPU; the inlining flags are Warp's defaults (they set speed,
  not results).
- ``fuse_fp`` False: every multiplication and addition rounds on its own, as written. Explicit
  fused multiply-adds in Warp's own built-ins (``fma``) stay single-rounded on every target (the C
  library's ``fma`` where the target lacks the instruction), so their bits do not move either.

Every DEM Warp module sets these with ``wp.set_module_options(MODULE_OPTIONS)``; kernels built
in their own module (``module="unique"``) pass them as ``module_options``. The kernels use ``+ - * /``
and sqrt only, which IEEE-754 rounds correctly, so the same compiled code gives the same
bits whatever the CPU's vector width. The cost in speed is measured by
``benchmarks/bench_dem_target.py`` (docs/determinism.md).
"""

CPU_COMPILER_FLAGS = ("-mllvm=-inline-threshold=9000 -mllvm=-inline-cold-callsite-threshold=3000"
                      " -mllvm=-slp-recursion-max-depth=4")
"""Clang/LLVM flags of the DEM's CPU kernels: Warp's default flags without ``-march=native``."""

MODULE_OPTIONS = {"enable_backward": False, "fuse_fp": False, "cpu_compiler_flags": CPU_COMPILER_FLAGS}
"""Warp module options of every DEM module: no adjoint kernels, no FMA contraction, generic x86-64."""
