# The two commands of the README. Both create or reuse .venv and install what they need.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
# Type checking in `make lint` with pyproject.toml's [tool.pyright] (basic; -p . so that no
# pyrightconfig.json above the checkout is picked up); PYRIGHT= skips it.
PYRIGHT ?= $(BIN)/pyright -p .
# On a Raspberry Pi the venv keeps the apt numpy picamera2 is built for: pip installs with
# constraints/<codename>.txt (README, On the Raspberry Pi). Elsewhere: none (today's stack).
ON_PI := $(shell grep -qs 'Raspberry Pi' /proc/device-tree/model && echo yes)
CODENAME := $(shell . /etc/os-release 2>/dev/null && echo $$VERSION_CODENAME)
CONSTRAINTS ?= $(if $(ON_PI),$(wildcard constraints/$(CODENAME).txt))
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml $(CONSTRAINTS) | cksum | cut -d' ' -f1)
# The Raspberry Pi OS Bookworm stack (Python 3.11, numpy 1.24, OpenCV 4.11): `make test` runs
# the suite on it as well, installed with the same constraints file as on the Pi. Without
# python3.11 it is skipped with a loud line, so the README's command works on any fresh
# machine; CI sets REQUIRE_BOOKWORM=1 so that a missing 3.11 fails instead (.ci/run).
PY_BOOKWORM ?= python3.11
REQUIRE_BOOKWORM ?=
BW_REQUIRED := $(filter-out 0,$(REQUIRE_BOOKWORM))
BW_FOUND := $(shell command -v $(PY_BOOKWORM) 2>/dev/null)
BW_VENV := .venv-bookworm
BW_BIN := $(BW_VENV)/bin
BW_STAMP := $(BW_VENV)/.installed-$(shell cat pyproject.toml constraints/bookworm.txt | cksum | cut -d' ' -f1)
# The project on the Pi's CPU: a Debian arm64 userland under qemu-user-static, installed as
# deploy/install.sh does, a kmead run compared with this machine's, the doctor, the Pi code
# paths' tests and the C decoder (scripts/test_arm64.sh; needs root). Without root or
# binfmt_misc it is skipped with a loud line; CI sets REQUIRE_ARM64=1 so that it fails
# instead (.ci/run). SKIP_ARM64=1 skips it on purpose (a machine without the time for it).
REQUIRE_ARM64 ?=
SKIP_ARM64 ?=
ARM64_CODENAME ?= bookworm
STACK = -c 'import sys, numpy, cv2; print("== suite on Python %d.%d.%d, numpy %s, OpenCV %s ==" % (*sys.version_info[:3], numpy.__version__, cv2.__version__))'
# Debian and Ubuntu ship venv's ensurepip in a separate package; without it `python -m venv`
# leaves a venv without pip and a traceback. $(call venv,PYTHON,DIR,OPTIONS) creates DIR or
# stops with one line naming the package to install.
define venv
test -x $(2)/bin/python || { \
	  command -v $(1) >/dev/null || { echo "make: $(1) not found"; exit 1; }; \
	  $(1) -c 'import venv, ensurepip' 2>/dev/null || { \
	    echo "make: $(1) cannot create a venv (no venv/ensurepip module): sudo apt install $$($(1) -c 'import sys; print("python%d.%d-venv" % sys.version_info[:2])' 2>/dev/null || echo python3-venv) (python3-venv for the system python3)"; exit 1; }; \
	  $(1) -m venv $(3) $(2); }
endef

.PHONY: run test test-current test-bookworm test-arm64 lint bench config install-service clean

$(STAMP): pyproject.toml
	@$(call venv,$(PY),$(VENV),$(if $(ON_PI),--system-site-packages))
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q $(if $(CONSTRAINTS),-c $(CONSTRAINTS)) -e '.[dev,plots]'
	rm -f $(VENV)/.installed-* && touch $@

$(BW_STAMP): pyproject.toml constraints/bookworm.txt
	@command -v $(PY_BOOKWORM) >/dev/null || { echo "make: $(PY_BOOKWORM) not found: the Bookworm stack needs Python 3.11 (install it, or PY_BOOKWORM=/path/to/python3.11)"; exit 1; }
	@$(call venv,$(PY_BOOKWORM),$(BW_VENV))
	$(BW_BIN)/python -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else "$(BW_VENV) is not Python 3.11: make clean")'
	$(BW_BIN)/python -m pip install -q --upgrade pip
	$(BW_BIN)/python -m pip install -q -c constraints/bookworm.txt -e '.[dev,plots]'
	rm -f $(BW_VENV)/.installed-* && touch $@

# The main job on the embedded default: the daemon, headless, on the simulated floor.
# Free ports: the job never collides with a running kmead (the Pi's service, another user);
# it prints the ports it bound. ARGS= passes more options (ARGS='--source sim:scenario2').
run: $(STAMP)
	$(BIN)/kmead --headless --free-ports --frames $${FRAMES:-300} --log out/run.csv $(ARGS)

# The suite on both stacks: today's (.venv) and Raspberry Pi OS Bookworm's (.venv-bookworm).
# ruff once, then the suite on each stack. On a Pi, .venv is the Pi's own stack (its
# constraints file, as for `make run`): the suite runs there and nowhere else.
test: lint test-current $(if $(ON_PI),$(if $(BW_REQUIRED),test-bookworm),test-bookworm) \
	$(if $(ON_PI),,test-arm64)

test-current: $(STAMP)
	@$(BIN)/python $(STACK)
	$(BIN)/python -m pytest -q -n 2 $(ARGS)

ifeq ($(BW_FOUND)$(BW_REQUIRED),)
test-bookworm:
	@echo "*** make: Bookworm stack SKIPPED: $(PY_BOOKWORM) not found; install Python 3.11 or run PY_BOOKWORM=/path/to/python3.11 make test-bookworm (CI: REQUIRE_BOOKWORM=1 make test) ***"
else ifeq ($(BW_FOUND),)
# Required but missing: fail at once, even beside a .venv-bookworm made earlier.
test-bookworm:
	@echo "make: $(PY_BOOKWORM) not found: the Bookworm stack needs Python 3.11 (install it, or PY_BOOKWORM=/path/to/python3.11)"; exit 1
else
test-bookworm: $(BW_STAMP)
	@$(BW_BIN)/python $(STACK)
	$(BW_BIN)/python -m pytest -q -n 2 $(ARGS)
endif

# The x86 run it is compared with: the Bookworm stack's (the Pi's numpy and OpenCV) where
# python3.11 is found, so that only the CPU differs; else today's stack.
ARM64_X86_BIN = $(abspath $(if $(BW_FOUND),$(BW_BIN),$(BIN)))
test-arm64: $(STAMP) $(if $(BW_FOUND),$(BW_STAMP))
	@if [ -n "$(filter-out 0,$(SKIP_ARM64))" ]; then \
	  if [ -n "$(filter-out 0,$(REQUIRE_ARM64))" ]; then echo "make: arm64 required (REQUIRE_ARM64=1) but SKIP_ARM64 is set"; exit 1; fi; \
	  echo "*** make: arm64 SKIPPED: SKIP_ARM64 is set; run REQUIRE_ARM64=1 make test-arm64 as root (CI does) ***"; \
	else REQUIRE_ARM64=$(filter-out 0,$(REQUIRE_ARM64)) ARM64_CODENAME=$(ARM64_CODENAME) BIN=$(ARM64_X86_BIN) scripts/test_arm64.sh; fi

# config.toml and the key table of docs/daemon.md, from the declarations in
# kmead/config/schema.py (a test fails when they disagree).
config: $(STAMP)
	$(BIN)/python -m kmead.config.schema

lint: $(STAMP)
	$(BIN)/ruff check .
	$(if $(PYRIGHT),$(PYRIGHT))

# The benchmarks without options of their own; every benchmark is `kmea bench NAME`
# (`kmea bench --list`).
bench: $(STAMP)
	$(BIN)/kmea bench

# On the Pi, as root: the systemd unit, its user and /etc/kmead (deploy/install.sh).
install-service:
	deploy/install.sh

clean:
	rm -rf $(VENV) $(BW_VENV) out .pytest_cache .ruff_cache
