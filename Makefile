# observer_ros: set-up, the closed-loop demo and the tests.
# `make demo` and `make test` each build the environment first (idempotent, quick when
# nothing changed): a virtual environment in .venv from requirements.txt, with the package
# installed into it.

PY := .venv/bin/python
STAMP := .venv/.observer_ros-installed
VEHICLE ?= config/submarine.yaml

.PHONY: setup demo test bench clean-venv

setup: $(STAMP)

$(STAMP): requirements.txt setup.py setup.cfg package.xml
	test -x $(PY) || python3 -m venv .venv
	$(PY) -m pip install --disable-pip-version-check -q -r requirements.txt
	$(PY) -m pip install --disable-pip-version-check -q --no-deps --use-pep517 -e . --config-settings editable_mode=compat
	touch $(STAMP)

demo: $(STAMP)
	.venv/bin/observer-run $(VEHICLE) --evaluate

test: $(STAMP)
	$(PY) -W ignore::DeprecationWarning -m pytest -q -p no:cacheprovider test

bench: $(STAMP)
	$(PY) benchmarks/run_all.py

clean-venv:
	rm -rf .venv
