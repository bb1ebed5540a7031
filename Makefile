# The two commands users need: `make demo` and `make test` (both set up first).
SHELL := /bin/bash
.SHELLFLAGS := -eo pipefail -c
.DEFAULT_GOAL := help

ROOT   := $(abspath .)
VENV   := $(ROOT)/.venv
# The catkin workspace lives outside the package tree, one per clone: inside it,
# rosrun's search (find -L over the package) met the workspace's own copies of
# every node and a link loop back to the package.  `source env.bash` finds it.
AMBOTS_WS ?= $(or $(XDG_CACHE_HOME),$(HOME)/.cache)/ambots/ws-$(shell printf %s '$(ROOT)' | md5sum | cut -c1-12)
WS     := $(AMBOTS_WS)
PY     := $(VENV)/bin/python
SITE   := $(VENV)/lib/python3.11/site-packages
# Debian 12's own ROS 1 and tools (see README for Ubuntu 20.04 + Noetic)
APT_PACKAGES := ros-core catkin python3-rospy python3-roslaunch python3-rostest \
  python3-rostopic python3-rosnode python3-rosparam python3-tf2-ros \
  python3-std-msgs python3-geometry-msgs python3-sensor-msgs python3-trajectory-msgs \
  python3-visualization-msgs python3-pykdl python3-numpy python3-yaml \
  python3-catkin-pkg librostest-dev python3-venv python3-dev ros-robot-state-publisher rviz xvfb \
  python3-rosgraph python3-rosgraph-msgs python3-roslib python3-rospkg prusa-slicer cmake g++ make rosbash
# everything a command needs: the workspace (ROS_PACKAGE_PATH, PYTHONPATH) and
# the venv first on PATH (done by the package's catkin env hook)
ROSENV := source $(WS)/devel/setup.bash &&

.PHONY: help setup apt venv workspace ws-path apt-packages test unit rostest soak bench faults demo print clean

help:
	@echo "make setup  - install what is missing (apt, .venv, catkin workspace)"
	@echo "make demo   - set up, then run the demo headless; outputs in out/demo"
	@echo "make test   - set up, then run every test (pytest + rostest)"
	@echo "make soak   - set up, then run the long tests (the demo at speed:=4, about 40 min)"
	@echo "make bench  - set up, then run the benchmarks"
	@echo "make faults - set up, then measure the fault figures (faults, kill -9, slowed arm, bad input)"
	@echo "make print MODEL=path OUT=dir [CELL= MODE= SLICER=] - print any model like the demo"

setup: apt venv workspace

# apt: only when a package is missing (a no-op check takes ~0.1 s)
apt:
	@missing=""; for p in $(APT_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing:$$missing"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -q && \
	  DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -q --no-install-recommends $$missing; \
	fi

venv: $(VENV)/.done
$(VENV)/.done: requirements.txt | apt
	[ -x $(PY) ] || /usr/bin/python3 -m venv --system-site-packages $(VENV)
	# keep Debian's numpy (PyKDL is built against it; numpy 2 makes it segfault)
	/usr/bin/python3 -c "import numpy; print('numpy==' + numpy.__version__)" > $(VENV)/constraints.txt
	# lines marked "# no-deps" are installed without their declared dependencies
	grep -v -- '# no-deps' requirements.txt > $(VENV)/requirements-deps.txt
	grep -- '# no-deps' requirements.txt > $(VENV)/requirements-nodeps.txt || true
	$(PY) -m pip install -q --disable-pip-version-check -r $(VENV)/requirements-deps.txt -c $(VENV)/constraints.txt
	$(PY) -m pip install -q --disable-pip-version-check --no-deps -r $(VENV)/requirements-nodeps.txt -c $(VENV)/constraints.txt
	echo "$(ROOT)/src" > $(SITE)/ambots-src.pth
	$(PY) -c "import numpy, PyKDL, trimesh, manifold3d, yourdfpy, xacro, ompl, pymeshfix; \
	  assert numpy.__file__.startswith('/usr/lib/python3/'), numpy.__file__"
	touch $@

workspace: $(WS)/devel/.done
$(WS)/devel/.done: package.xml CMakeLists.txt setup.py $(wildcard nodes/* tests/ros/*.test config/env-hooks/*) | apt venv
	@# a workspace of the old layout inside the package (.ws/) would be searched by rosrun again
	rm -rf $(ROOT)/.ws
	@# workspaces of clones that are gone (their link to the package dangles)
	@for d in $(dir $(WS))ws-*; do [ -e "$$d/src/ambots/package.xml" ] || rm -rf "$$d"; done
	mkdir -p $(WS)/src && ln -sfn $(ROOT) $(WS)/src/ambots
	cd $(WS) && catkin_make -DPYTHON_EXECUTABLE=/usr/bin/python3 -DCATKIN_ENABLE_TESTING=ON > build.log 2>&1 \
	  || { tail -40 build.log; exit 1; }
	touch $@

test: setup
	$(ROSENV) cd $(ROOT) && $(PY) -m pytest tests --ignore=tests/soak

# the long tests (tests/soak: the demo at speed:=4, about 40 min of wall time)
soak: setup
	$(ROSENV) cd $(ROOT) && $(PY) -m pytest tests/soak

unit: setup
	$(ROSENV) cd $(ROOT) && $(PY) -m pytest tests/unit

rostest: setup
	$(ROSENV) cd $(ROOT) && $(PY) -m pytest tests/ros

bench: setup
	$(ROSENV) cd $(ROOT) && $(PY) tests/bench/run.py

# the fault figures (README): dropped/duplicated/reordered messages, kill -9, a slowed arm, hostile input
faults: setup
	$(ROSENV) cd $(ROOT) && $(PY) tests/bench/run.py faults

# DEMO_OUT: where the demo writes (tests/ros/test_demo.py runs `make demo` into a temporary folder)
DEMO_OUT ?= out/demo
demo: setup
	@rm -rf "$(DEMO_OUT)" && mkdir -p "$(DEMO_OUT)"
	@echo "make demo: the demo model printed by both arms, headless (about three minutes); log in $(DEMO_OUT)/launch.log"
	@$(ROSENV) roslaunch ambots demo.launch out:="$(abspath $(DEMO_OUT))" > "$(DEMO_OUT)/launch.log" 2>&1 \
	  || { tail -30 "$(DEMO_OUT)/launch.log"; echo "roslaunch failed: whole log in $(DEMO_OUT)/launch.log"; }
	@echo; $(PY) -m ambots summary --capture "$(DEMO_OUT)"

# any model, the same way: make print MODEL=path [CELL=...] [MODE=...] [SLICER=...] [SPEED=max] [ARMS=a,b] OUT=dir
MODE ?= concurrent
SEAM ?= straight
SLICER ?= builtin
SPEED ?= max
print: setup
	@[ -n "$(MODEL)" ] && [ -n "$(OUT)" ] || { echo "usage: make print MODEL=path OUT=dir [CELL=...] [MODE=...] [SEAM=...] [SLICER=...]"; exit 2; }
	@mkdir -p "$(OUT)"
	@echo "make print: $(MODEL) headless; log in $(OUT)/launch.log"
	@$(ROSENV) roslaunch ambots demo.launch out:="$(abspath $(OUT))" model:="$(abspath $(MODEL))" \
	  mode:=$(MODE) seam:=$(SEAM) slicer:=$(SLICER) speed:=$(SPEED) $(if $(CELL),cell:="$(abspath $(CELL))") $(if $(ARMS),arms:="$(ARMS)") \
	  > "$(OUT)/launch.log" 2>&1 || { tail -30 "$(OUT)/launch.log"; echo "roslaunch failed: whole log in $(OUT)/launch.log"; }
	@echo; $(PY) -m ambots summary --capture "$(OUT)"

# where the workspace is (env.bash asks), and what apt installs (tests/unit/test_dependencies.py asks)
ws-path:
	@echo $(WS)
apt-packages:
	@echo $(APT_PACKAGES)

clean:
	rm -rf $(WS) out
