# make test : create .venv, install the package (CPU torch first), run the CI test suite
# make demo : same set-up, then the constant-volume biaxial demo figures
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
export WARP_CACHE_PATH := $(CURDIR)/.warp_cache
export MPLBACKEND := Agg

.PHONY: venv test demo bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install torch==2.13.0
	$(PY) -m pip install -e '.[dev]'
	touch $@

venv: $(VENV)/.installed

test: venv
	$(PY) -m pytest -q

demo: venv
	$(PY) -m homogenization.biaxial --backend analytical --alpha0 55 --p0 5.85e6 --eps-max 0.2 --out demo/alpha55 --overwrite
	$(PY) -m homogenization.biaxial --backend analytical --alpha0 40 --p0 5.85e6 --eps-max 0.2 --out demo/alpha40 --overwrite
	@echo "Figures: demo/alpha55/cambridge.png demo/alpha40/cambridge.png"

clean:
	rm -rf $(VENV) .warp_cache demo
