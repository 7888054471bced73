# observer_ros: set-up, the closed-loop demo and the tests.
# `make demo` and `make test` each build the environment first (idempotent, quick when
# nothing changed): a virtual environment in .venv from requirements.txt, with the package
# installed into it.

PY := .venv/bin/python
STAMP := .venv/.observer_ros-installed
VEHICLE ?= config/submarine.yaml
# more options for observer-run, e.g. ARGS='-p simulator.duration:=10.0'
ARGS ?=
TOOLS := observer_design observer_eval observer_eval_batch observer_tune observer_play observer_run \
	observer_bag_recover
ROS2CLI := ../shared/ros2cli
# the kit's files: a changed wheel or install script makes `make setup` install it again
KIT_FILES := $(wildcard $(ROS2CLI)/install.sh $(ROS2CLI)/wheels/*.whl)
KIT_SUM := .venv/.ros2cli-kit.sha256

.PHONY: setup compile demo test check bench clean-venv

setup: $(STAMP)

# uv (from PyPI) resolves and installs requirements.txt with the index pages and wheels
# fetched in parallel; pip fetched them one after another. The kit's own dependencies
# (install.sh's first pip line) go into the same resolve, so install.sh finds them there,
# and pip itself, which install.sh runs.
UV := .venv/bin/uv
KIT_DEPS := $(if $(wildcard $(ROS2CLI)/install.sh),pip osrf-pycommon lark argcomplete psutil \
	netifaces packaging pyyaml)

# The venv is made without pip, and uv installed into it by the base interpreter's pip
# (its --python option, pip >= 22.3): 2.5 s, where a venv with pip and then pip installing
# uv took 6.6 s (pip, installed by uv below, is then compiled with the rest: 1.1 s). Where
# the base interpreter has no such pip, ensurepip puts one into the venv first.
$(STAMP): requirements.txt setup.py setup.cfg package.xml $(KIT_FILES) Makefile
	test -x $(PY) || python3 -m venv --without-pip .venv
	test -x $(UV) || python3 -m pip --python $(PY) install --disable-pip-version-check -q \
	  uv==0.13.8 || { $(PY) -m ensurepip >/dev/null && \
	  $(PY) -m pip install --disable-pip-version-check -q uv==0.13.8; }
	$(UV) pip install -q --python $(PY) -r requirements.txt $(KIT_DEPS)
	$(UV) pip install -q --python $(PY) --no-deps -e . --config-settings editable_mode=compat
	# the tools' dash names (observer-run, ...): aliases in the venv only; lib/observer_ros
	# of a colcon install has the underscore names alone (`ros2 pkg executables`)
	for exe in $(TOOLS); do ln -sf $$exe .venv/bin/$$(echo $$exe | tr _ -); done
	# the real ros2 client and ros2 launch (test/test_ros2cli.py), when the kit is there;
	# installed again when its wheels or script differ from those last installed (their
	# checksum; install.sh alone only compares its own date)
	if [ -d $(ROS2CLI) ]; then \
	  sum=$$(cat $(KIT_FILES) | sha256sum | cut -d' ' -f1); \
	  if [ "$$sum" != "$$(cat $(KIT_SUM) 2>/dev/null)" ]; then \
	    rm -f .venv/.ros2cli-kit-installed; fi; \
	  $(ROS2CLI)/install.sh .venv && echo "$$sum" > $(KIT_SUM); fi
	# every installed module compiled to bytecode (uv, unlike pip, leaves them uncompiled):
	# where PYTHONDONTWRITEBYTECODE is set (it is on these machines) every process would
	# otherwise compile scipy, python-control and rclpy from source at each start (the
	# observer node's imports 3.6 s of CPU instead of 1.2 s); 2 s when all are compiled.
	# The installed packages' own tests/ folders (never imported here) are left out: 10.5 s
	# of CPU instead of 17.9 s on a new environment
	$(PY) -m compileall -q -j 0 -x '/tests/' \
	  $$($(PY) -c 'import sysconfig; print(sysconfig.get_path("purelib"))')
	touch $(STAMP)

# the package's own modules compiled as they are now (an editable install is not compiled
# by the installer; only the files changed since the last run are compiled again)
compile: $(STAMP)
	$(PY) -m compileall -q observer_ros

demo: compile
	.venv/bin/observer-run $(VEHICLE) --evaluate $(ARGS)

# the whole suite (CI): every test but those marked realtime in TEST_WORKERS processes, each
# in its own DDS domain (the ros tests among them wait on conditions, not on the clock), at
# a lower priority (nice WORKERS_NICE); beside them, the realtime ones (closed loops of
# unstable plants, rates, latencies) one at a time at the normal priority, in a domain of
# their own below the workers' range, so that the scheduler hands them first the CPU they
# ask for (about 9/10 of it where they contend at nice 10; a worker's process gets about
# 1/9, where nice 19 would give it 1/70). The realtime report is printed when the others are
# done. Beside each other at one priority on 2 cores, realtime tests failed 1-3 different
# ones per run.
# pytest keeps each test module as rewritten for its assertions in test/'s __pycache__
# folders, and the test helpers compiled, where PYTHONDONTWRITEBYTECODE (set on these
# machines) would have every worker rewrite and compile them again at each run: 2.7 s of CPU
# per pytest process to collect make check's tests (6.6 s without the cache, 3.5 s with it)
PYTEST := env PYTHONDONTWRITEBYTECODE= $(PY) -W ignore::DeprecationWarning -m pytest
# 6 workers: their processes wait on DDS discovery and on one another; 4 kept 1.82 of the 2
# cores busy (1027 s of CPU in 564 s), 6 kept 1.87 and 1.92 (971 s in 518 s, 1045 s in
# 544 s; fresh clones, 2026-11-28)
TEST_WORKERS ?= 6
REALTIME_DOMAIN_ID ?= 99
WORKERS_NICE ?= 10
test: compile
	rc=0; log=$$(mktemp); \
	OBSERVER_TEST_DOMAIN_ID=$(REALTIME_DOMAIN_ID) $(PYTEST) \
	  -q -p no:cacheprovider -m realtime test > $$log 2>&1 & realtime=$$!; \
	nice -n $(WORKERS_NICE) $(PYTEST) -q -p no:cacheprovider \
	  -n $(TEST_WORKERS) --maxschedchunk 2 -m "not realtime" test || rc=$$?; \
	wait $$realtime || rc=$$?; \
	echo "== the realtime tests (run beside the others, at the normal priority):"; \
	cat $$log; rm -f $$log; \
	exit $$rc

# after each change: every test that starts no process and no DDS participant, one worker
# per core. In both: the longest tests first (conftest.py), handed out two at a time as
# workers free up (--maxschedchunk), so that no worker is left alone with them at the end
CHECK_WORKERS ?= 2
check: compile
	$(PYTEST) -q -p no:cacheprovider -n $(CHECK_WORKERS) \
	  --maxschedchunk 2 -m "not ros" test

bench: compile
	$(PY) benchmarks/run_all.py

clean-venv:
	rm -rf .venv
