# make test      : create .venv, install the package (CPU torch first), run the CI test suite in
#                  TEST_WORKERS processes (default 2)
# make demo      : same set-up, then the constant-volume biaxial tests and their figures
# make docs      : same set-up plus the docs extra, then the documentation site (warnings are errors)
#                  into docs/_build/html/index.html
# make figures   : same set-up, then redraws the docs' figures that hmodel commands draw (the three
#                  backends overlaid, the two triaxial tests) into docs/figures/; the benchmark
#                  and study scripts draw the others (docs/benchmarks.md, studies/README.md)
# make bench     : speed benchmarks (numbers quoted in README)
# make determinism: the tests marked determinism under every CPU-feature setting of numpy, OpenBLAS, glibc,
#                  torch and numba (docs/determinism.md)
# make reproduce : the whole pipeline from scratch: DEM database (6e5), training, active-learning
#                  rounds on the certificate's failing tests (docs/certificate.md), three backends.
#                  The shipped 2D model is this pipeline's (docs/studies/ann_narrow_network.md)
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
export WARP_CACHE_PATH := $(CURDIR)/.warp_cache
export MPLBACKEND := Agg
# Python keeps the bytecode it compiles: uv, unlike pip, compiles none at install (.ci/uv_pip_install.py)
unexport PYTHONDONTWRITEBYTECODE

BIAXIAL := $(PY) -m homogenization.biaxial --overwrite
# The three backends overlaid; shear and isotropic increments of 1e-4 keep every backend
# within 0.1 % of p0 of its converged curve (docs/dem_homogenization.md).
OVERLAY := --increment 1e-4 --iso-increment 1e-4 --orientations 360 --eps-max 0.2

.PHONY: venv test determinism docs demo figures bench reproduce clean clean-kernels

# uv installs what pip would (pip's configuration, .ci/uv_pip_install.py), faster from a cold cache.
UV_PIP_INSTALL := $(PY) .ci/uv_pip_install.py

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install uv
	$(UV_PIP_INSTALL) torch==2.13.0
	$(UV_PIP_INSTALL) -e '.[dev]'
	touch $@

venv: $(VENV)/.installed

# The suite in TEST_WORKERS processes (pytest-xdist): 2 fills the 2-core CI machine. Work stealing:
# each worker takes half of the tests in order and an idle one takes over the rest of the other's,
# so neither waits long at the end.
TEST_WORKERS ?= 2

test: venv
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist worksteal

determinism: venv
	$(PY) tests/determinism_settings.py

$(VENV)/.docs-installed: $(VENV)/.installed
	$(UV_PIP_INSTALL) -e '.[dev,docs]'
	touch $@

# A fresh build every time (no stale API stubs, every warning shown again); no network needed.
docs: $(VENV)/.docs-installed
	rm -rf docs/_build docs/_autosummary
	$(PY) -m sphinx -b html -W --keep-going -q docs docs/_build/html
	@! grep -l "cdn.jsdelivr.net\|mathjax@" docs/_build/html/*.html || (echo "a page loads MathJax from a CDN"; exit 1)
	@echo "Site: docs/_build/html/index.html"

# The shipped 2D ANN's certificate covers p0 = 2e5 to 1e6 N/m and eps1 <= 10 % (docs/ann.md): the ANN
# runs at p0 = 2e5 to 10 % and is overlaid (hmodel plot) on the closed form and the DEM, which go on to 20 %.
ANN_OVERLAY := --increment 1e-4 --iso-increment 1e-4 --orientations 360 --eps-max 0.1
# The shipped 3D ANN beside the closed form, inside its certificate (hcell3d:alpha0=55, p0 = 2e5 to 1e6 Pa, 10 %);
# its first run on a machine compiles the spatial kernels (~25 s), which later runs then find cached.
ANN3D_DEMO := --p0 2e5 --undrained --eps-max 0.1 --increment 1e-4 --order 11 --spins 4

demo: venv
	$(BIAXIAL) --backend analytical,dem --alpha0 55 --p0 5.85e6 $(OVERLAY) --out demo/alpha55
	$(BIAXIAL) --backend analytical,dem --alpha0 55 --p0 2e5 $(OVERLAY) --out demo/alpha55_low
	$(BIAXIAL) --backend ann --alpha0 55 --p0 2e5 $(ANN_OVERLAY) --out demo/alpha55_low_ann
	$(PY) -m homogenization.plotting --overwrite demo/alpha55_low/analytical/run.h5 demo/alpha55_low/dem/run.h5 \
		demo/alpha55_low_ann/run.h5 --out demo/alpha55_low/cambridge.png
	$(BIAXIAL) --backend analytical --alpha0 40 --p0 5.85e6 --out demo/alpha40
	$(PY) -m homogenization.triaxial --overwrite --backend analytical,ann --mesostructure hcell3d:alpha0=55 $(ANN3D_DEMO) \
		--out demo/triaxial55
	@echo "Figures (q-eps1, Cambridge plane q-p, p-eps1, q/p-eps1; 3D: stress path, deviator, volume):"
	@ls -1 demo/*/cambridge.png demo/triaxial55/triaxial.png

FIGURES := runs/figures
TRIAXIAL := $(PY) -m homogenization.triaxial --overwrite --backend analytical,dem --p0 2e5 --eps-max 0.15 \
	--increment 1e-4 --order 11 --spins 4

figures: venv
	$(BIAXIAL) --backend analytical,dem --alpha0 55 --p0 5.85e6 $(OVERLAY) --out $(FIGURES)/a55_p5.85e6
	$(BIAXIAL) --backend analytical,dem --alpha0 55 --p0 2e5 $(OVERLAY) --out $(FIGURES)/a55_p2e5
	$(BIAXIAL) --backend ann --alpha0 55 --p0 2e5 $(ANN_OVERLAY) --out $(FIGURES)/a55_p2e5_ann
	$(PY) -m homogenization.plotting --overwrite $(FIGURES)/a55_p2e5/analytical/run.h5 $(FIGURES)/a55_p2e5/dem/run.h5 \
		$(FIGURES)/a55_p2e5_ann/run.h5 --out $(FIGURES)/a55_p2e5/cambridge.png
	$(TRIAXIAL) --mesostructure hcell3d:alpha0=55 --undrained --out $(FIGURES)/tx55
	$(TRIAXIAL) --mesostructure hcell3d:alpha0=47 --drained --out $(FIGURES)/tx47
	cp $(FIGURES)/a55_p5.85e6/cambridge.png docs/figures/analytical_dem_a55_p5.85e6.png
	cp $(FIGURES)/a55_p2e5/cambridge.png docs/figures/three_backends_a55_p2e5.png
	cp $(FIGURES)/tx55/triaxial.png docs/figures/triaxial_a55_p2e5_undrained.png
	cp $(FIGURES)/tx47/triaxial.png docs/figures/triaxial_a47_p2e5_drained.png

bench: venv
	$(PY) benchmarks/bench_homogenization.py
	$(PY) benchmarks/bench_dem_kernel.py
	$(PY) benchmarks/bench_dem_homogenization.py
	$(PY) benchmarks/bench_generate.py
	$(PY) benchmarks/bench_ann.py
	$(PY) benchmarks/bench_dem_stepping.py --quick
	$(PY) benchmarks/bench_bvp.py
	$(PY) benchmarks/bench_sweep.py

# hmodel train: training, certificate and active-learning rounds (at most 10 x 20,000 probes of
# the failing tests' DEM states; each round fine-tunes the kept 2 x 24 model, --warm-start, with
# the rounds' samples carrying 30 % of the loss, --round-share 0.3; a round is kept only where it
# beats the model kept; docs/certificate.md, docs/studies/reproduce_rounds.md).
# A 2 x 24 network, seed 1: its step costs 0.71x the closed form's (2 x 40: 0.93x), its certificate 0.208 %
# (seed 0: 1.293 %; docs/studies/ann_narrow_network.md).
reproduce: venv
	mkdir -p runs
	$(PY) -m warp_hcell.generate --samples 600000 --seed 0 --threads 1 --sample-spacing 2.5e-3 --perturbed-fraction 0.4 --out runs/db_6e5.h5 --overwrite
	$(PY) -m homogenization.train --data runs/db_6e5.h5 --out runs/ann.pt --overwrite --no-widen --rounds 10 --max-samples 200000 --stall-rounds 3 --warm-start --round-share 0.3 --hidden 24,24 --seed 1
	$(BIAXIAL) --backend analytical,dem,ann --model runs/ann.pt --alpha0 55 --p0 5.85e6 $(OVERLAY) --out runs/alpha55
	@echo "Figure: runs/alpha55/cambridge.png"

# numba keys a kernel's cache on the kernel's own file: after editing a module a kernel calls, drop every
# compiled kernel (numba's caches beside the sources and the precompiled steps) so that the next run compiles.
clean-kernels:
	find warp_hcell training homogenization -path '*/__pycache__/*' \( -name '*.nbi' -o -name '*.nbc' \) -delete
	rm -rf training/__pycache__/precompiled

clean:
	rm -rf $(VENV) .warp_cache demo docs/_build docs/_autosummary
