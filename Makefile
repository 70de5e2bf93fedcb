# The two commands of the README: `make demo` and `make test`. Each creates .venv when missing
# and installs the project into it, so a fresh machine needs nothing else.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install test demo clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install -e '.[test]'
	@touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q

# `make demo`: VIRGi on the bundled capture (CPU: a few minutes); `make demo FULL=1`: full resolution (GPU).
# `make demo SPLAT=path/to/scene.ply`: recolour any splat file with no photos (demo_out/splat/).
ifndef SPLAT
demo: $(STAMP)
	$(PY) -m virgi_ns.demo --out demo_out $(if $(FULL),--full,)
endif

ifdef SPLAT
demo: $(STAMP)
	$(PY) -m virgi_ns.demo.splat --splat $(SPLAT) --out demo_out/splat
endif

clean:
	rm -rf $(VENV) demo_out
