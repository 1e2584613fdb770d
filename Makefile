# The two commands of the README. Both create or reuse .venv and install what they need.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
# On a Raspberry Pi the venv keeps the apt numpy picamera2 is built for: pip installs with
# constraints/<codename>.txt (README, On the Raspberry Pi). Elsewhere: none (today's stack).
ON_PI := $(shell grep -qs 'Raspberry Pi' /proc/device-tree/model && echo yes)
CODENAME := $(shell . /etc/os-release 2>/dev/null && echo $$VERSION_CODENAME)
CONSTRAINTS ?= $(if $(ON_PI),$(wildcard constraints/$(CODENAME).txt))
STAMP := $(VENV)/.installed-$(shell cat pyproject.toml $(CONSTRAINTS) | cksum | cut -d' ' -f1)
# The Raspberry Pi OS Bookworm stack (Python 3.11, numpy 1.24, OpenCV 4.11): `make test` runs
# the suite on it as well, installed with the same constraints file as on the Pi.
PY_BOOKWORM ?= python3.11
BW_VENV := .venv-bookworm
BW_BIN := $(BW_VENV)/bin
BW_STAMP := $(BW_VENV)/.installed-$(shell cat pyproject.toml constraints/bookworm.txt | cksum | cut -d' ' -f1)
STACK = -c 'import sys, numpy, cv2; print("== suite on Python %d.%d.%d, numpy %s, OpenCV %s ==" % (*sys.version_info[:3], numpy.__version__, cv2.__version__))'

.PHONY: run test test-current test-bookworm lint bench install-service clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(if $(ON_PI),--system-site-packages) $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q $(if $(CONSTRAINTS),-c $(CONSTRAINTS)) -e '.[dev,plots]'
	rm -f $(VENV)/.installed-* && touch $@

$(BW_STAMP): pyproject.toml constraints/bookworm.txt
	@command -v $(PY_BOOKWORM) >/dev/null || { echo "make: $(PY_BOOKWORM) not found: the Bookworm stack needs Python 3.11 (PY_BOOKWORM=...)"; exit 1; }
	test -x $(BW_BIN)/python || $(PY_BOOKWORM) -m venv $(BW_VENV)
	$(BW_BIN)/python -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else "$(BW_VENV) is not Python 3.11: make clean")'
	$(BW_BIN)/python -m pip install -q --upgrade pip
	$(BW_BIN)/python -m pip install -q -c constraints/bookworm.txt -e '.[dev,plots]'
	rm -f $(BW_VENV)/.installed-* && touch $@

# The main job on the embedded default: the daemon, headless, on the simulated floor.
run: $(STAMP)
	$(BIN)/kmead --headless --frames $${FRAMES:-300} --log out/run.csv

# The suite on both stacks: today's (.venv) and Raspberry Pi OS Bookworm's (.venv-bookworm).
# ruff once, then the suite on each stack.
test: lint test-current test-bookworm

test-current: $(STAMP)
	@$(BIN)/python $(STACK)
	$(BIN)/python -m pytest -q -n 2 $(ARGS)

test-bookworm: $(BW_STAMP)
	@$(BW_BIN)/python $(STACK)
	$(BW_BIN)/python -m pytest -q -n 2 $(ARGS)

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/kmea bench

# On the Pi, as root: the systemd unit, its user and /etc/kmead (deploy/install.sh).
install-service:
	deploy/install.sh

clean:
	rm -rf $(VENV) $(BW_VENV) out .pytest_cache .ruff_cache
