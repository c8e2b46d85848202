# The README's two commands: `make run` and `make test`. Both build .venv first.
# `make install` / `make upgrade` / `make uninstall` put azimuthd on a companion computer (run as root);
# DESTDIR= stages everything under another root (packaging, tests).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

# where the install goes (the unit file's ExecStart= and Documentation= point here)
PREFIX ?= /usr/local
INSTALL_VENV ?= /opt/azimuthd
SYSCONFDIR ?= /etc
UNITDIR ?= /etc/systemd/system
DOCDIR ?= $(PREFIX)/share/doc/azimuthd
# extras for the companion computer: none by default; e.g. EXTRAS=tui for `azimuthd watch`
EXTRAS ?=
PIP_OPTS ?=
# a wheel to install instead of building one from this tree (tests, offline installs)
WHEEL ?=
DOCS := README.md docs/VEHICLE.md docs/OUTPUTS.md docs/SECURITY.md docs/GEOFENCE.md docs/REPLAY.md docs/SIMULATOR.md
DIST := build/dist

SVC_PY := $(DESTDIR)$(INSTALL_VENV)/bin/python
THE_WHEEL = $(or $(WHEEL),$$(ls $(DIST)/azimuthd-*.whl))

.PHONY: run test venv clean wheel install upgrade uninstall

venv: $(STAMP)

# the compiled core is built at install time (scikit-build-core): its sources re-run the install
$(STAMP): pyproject.toml CMakeLists.txt $(wildcard core/*.cpp core/*.hpp)
	$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "azimuthd needs Python >= 3.11")'
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,bench]'
	touch $(STAMP)

run: $(STAMP)
	$(PY) bench/live_demo.py

# two workers: the tests that run processes in real time are one unit on one worker, one after
# another; the CPU-bound rest beside them, a module at a time (tests/conftest.py). TEST_WORKERS=0:
# one process.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(PY) -m pytest -q $(if $(filter-out 0,$(TEST_WORKERS)),-n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder) --durations=25 tests

# a wheel of this tree, built by the service venv's pip (what install and upgrade put in it); DESTDIR
# is kept from the build (CMake's install step into the wheel would honour it and miss the wheel)
wheel: $(SVC_PY)
	$(if $(WHEEL),@echo "using $(WHEEL)",rm -rf $(DIST) && env -u DESTDIR $(SVC_PY) -m pip wheel --quiet --no-deps --wheel-dir $(DIST) .)

$(SVC_PY):
	$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "azimuthd needs Python >= 3.11")'
	$(PYTHON) -m venv $(DESTDIR)$(INSTALL_VENV)

install: wheel
	$(SVC_PY) -m pip install --quiet $(PIP_OPTS) "$(THE_WHEEL)$(if $(EXTRAS),[$(EXTRAS)])"
	install -d $(DESTDIR)$(PREFIX)/bin
	ln -sfn $(INSTALL_VENV)/bin/azimuthd $(DESTDIR)$(PREFIX)/bin/azimuthd
	install -D -m 0644 systemd/azimuthd.service $(DESTDIR)$(UNITDIR)/azimuthd.service
	install -d -m 0755 $(DESTDIR)$(SYSCONFDIR)/azimuthd
	@# the config is the operator's: installed once, never overwritten (the example stays beside the docs)
	test -e $(DESTDIR)$(SYSCONFDIR)/azimuthd/azimuthd.toml || \
		install -m 0644 systemd/azimuthd.toml $(DESTDIR)$(SYSCONFDIR)/azimuthd/azimuthd.toml
	install -d $(DESTDIR)$(DOCDIR)
	install -m 0644 $(DOCS) systemd/azimuthd.toml $(DESTDIR)$(DOCDIR)/
	@if [ -z "$(DESTDIR)" ] && command -v systemctl >/dev/null 2>&1 && [ -d /run/systemd/system ]; then \
		systemctl daemon-reload; fi
	@echo "installed: $(PREFIX)/bin/azimuthd -> $(INSTALL_VENV), $(UNITDIR)/azimuthd.service, docs in $(DOCDIR)"
	@echo "next: set [site] and [mavlink] url in $(SYSCONFDIR)/azimuthd/azimuthd.toml (docs/VEHICLE.md), then"
	@echo "      systemctl enable --now azimuthd && journalctl -u azimuthd -f"

# the new code, unit and docs; the config and the calibrations (/var/lib/azimuthd) are kept
upgrade:
	@test -x $(SVC_PY) || { echo "azimuthd is not installed in $(DESTDIR)$(INSTALL_VENV): run make install"; exit 1; }
	$(MAKE) --no-print-directory wheel
	$(SVC_PY) -m pip install --quiet --force-reinstall --no-deps $(PIP_OPTS) "$(THE_WHEEL)"
	$(SVC_PY) -m pip install --quiet $(PIP_OPTS) "$(THE_WHEEL)$(if $(EXTRAS),[$(EXTRAS)])"
	install -D -m 0644 systemd/azimuthd.service $(DESTDIR)$(UNITDIR)/azimuthd.service
	install -d $(DESTDIR)$(DOCDIR)
	install -m 0644 $(DOCS) systemd/azimuthd.toml $(DESTDIR)$(DOCDIR)/
	@if [ -z "$(DESTDIR)" ] && command -v systemctl >/dev/null 2>&1 && [ -d /run/systemd/system ]; then \
		systemctl daemon-reload && systemctl try-restart azimuthd; fi
	@echo "upgraded to $$($(DESTDIR)$(INSTALL_VENV)/bin/azimuthd --version); config and calibrations kept"

# removes the code, the unit and the docs; keeps the config and the calibrations (say so)
uninstall:
	@if [ -z "$(DESTDIR)" ] && command -v systemctl >/dev/null 2>&1 && [ -d /run/systemd/system ]; then \
		systemctl disable --now azimuthd 2>/dev/null || true; fi
	rm -f $(DESTDIR)$(UNITDIR)/azimuthd.service
	rm -f $(DESTDIR)$(PREFIX)/bin/azimuthd
	rm -rf $(DESTDIR)$(INSTALL_VENV) $(DESTDIR)$(DOCDIR)
	@if [ -z "$(DESTDIR)" ] && command -v systemctl >/dev/null 2>&1 && [ -d /run/systemd/system ]; then \
		systemctl daemon-reload; fi
	@echo "removed; kept: $(SYSCONFDIR)/azimuthd/ (config, signing key) and /var/lib/azimuthd (calibrations)"

clean:
	rm -rf $(VENV) build *.egg-info
