# Two commands do everything on a fresh machine: `make demo` and `make test`.
# Every process that may start rclpy keeps DDS on loopback.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export RMW_IMPLEMENTATION := rmw_fastrtps_cpp
export PYTHONDONTWRITEBYTECODE := 1

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
# tf2_msgs and apriltag_msgs generated into the venv (scripts/build_ros_interfaces.py says why).
INTERFACES := $(VENV)/.interfaces-stamp

.PHONY: demo test bench install clean bpy-venv

install: $(STAMP) $(INTERFACES)

REQUIREMENTS := requirements.txt requirements-extras.txt requirements-test.txt \
	requirements-interfaces.txt

$(STAMP): $(REQUIREMENTS) setup.py package.xml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	# A venv's bundled pip may predate PEP 660 editable installs of an ament_python setup.cfg.
	$(PY) -m pip install --quiet --disable-pip-version-check pip==26.3
	$(PY) -m pip install --quiet --disable-pip-version-check $(addprefix -r ,$(REQUIREMENTS))
	$(PY) -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e .
	touch $(STAMP)

$(INTERFACES): $(STAMP) scripts/build_ros_interfaces.py $(wildcard ficap_ros/interfaces/*/msg/*.msg)
	$(PY) scripts/build_ros_interfaces.py --venv $(VENV)
	touch $(INTERFACES)

demo: $(STAMP) $(INTERFACES)
	ROS_DOMAIN_ID=$${ROS_DOMAIN_ID:-77} $(PY) -m ficap_ros.cli demo

test: $(STAMP) $(INTERFACES)
	$(PY) -m pytest

# Every benchmark in turn (each writes its section of docs/benchmarks.md); BENCH_ARGS=--quick is
# the fast mode. A caller's ROS_DOMAIN_ID is kept (the node benchmarks start rclpy).
BENCH_ARGS ?=
bench: $(STAMP) $(INTERFACES)
	@set -e; start=$$(date +%s); for script in benchmarks/bench_*.py; do \
		echo "== $$script $(BENCH_ARGS)"; t0=$$(date +%s); \
		ROS_DOMAIN_ID=$${ROS_DOMAIN_ID:-70} $(PY) $$script $(BENCH_ARGS) > /dev/null; \
		echo "== $$script: $$(( $$(date +%s) - t0 )) s"; \
	done; echo "== make bench: $$(( $$(date +%s) - start )) s"

# Blender as a Python module, for datasets/cycles_render.py only (the package never imports bpy;
# `make test` does not need it). CPython 3.11, manylinux x86_64; the wheel brings numpy 1.26.
bpy-venv:
	test -x .venv-bpy/bin/python || python3.11 -m venv .venv-bpy
	.venv-bpy/bin/python -m pip install --quiet --disable-pip-version-check bpy==5.0.1

clean:
	rm -rf $(VENV) build install log *.egg-info
