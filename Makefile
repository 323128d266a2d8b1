# The two commands of the README. Both set everything up on a fresh machine (venv + install).
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: demo test bench

demo: $(STAMP)
	$(VENV)/bin/racecav demo

test: $(STAMP)
	$(VENV)/bin/pytest -q

$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	# torch is pinned to the CPU wheel (torch==2.13.0) in pyproject.toml: never a CUDA build.
	$(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)
