# Two entry points: `make demo` (the main job) and `make test` (`make coverage` measures it). Each sets up its own venv.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: demo test coverage venv system-deps clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test,bench]'
	touch $@

# Then the package's bytecode, written here: an editable install has none, and
# with PYTHONDONTWRITEBYTECODE set every robot process would compile coapkb's
# modules again (0.4 s of CPU each: a 99-robot team's start-up on two cores).
venv: $(VENV)/.installed
	@$(PY) -m compileall -q coapkb >/dev/null

# Debian packages used by the interop and link-emulation tests (needs root; skipped otherwise).
# iptables: its NFQUEUE target feeds the link emulator's delay line (this kernel's nftables has no queue).
# tshark: Wireshark's dissectors, for the byte budget's RTPS (experiments/byte_budget_peers.py); asked
# whether non-root users may capture, it is told no.
system-deps:
	@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  command -v coap-client-notls >/dev/null && command -v nft >/dev/null && command -v tc >/dev/null \
	    && command -v iptables >/dev/null && command -v tshark >/dev/null || { \
	    echo "wireshark-common wireshark-common/install-setuid boolean false" | debconf-set-selections; \
	    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libcoap3-bin nftables iproute2 iptables \
	      tshark >/dev/null; }; \
	else echo "system-deps: not root or no apt-get; interop/netns tests will skip"; fi

demo: venv
	$(VENV)/bin/coapkb demo

# Three workers on two cores: a third of the suite waits on timers and robot processes, not the
# CPU (two workers kept 1.5 cores busy); 663 s against 758 s on a clean clone, one run each.
PYTEST := $(PY) -m pytest -q -n 3 --dist loadfile --durations=15

test: venv system-deps
	$(PYTEST)

# The same suite with coverage measured (robots run as processes included, [tool.coverage] in
# pyproject.toml): a figure, not a gate, and not in `make test`, whose in-process tests its
# line tracer made about 1.6x slower.  The total line is printed even when a test fails.
coverage: venv system-deps
	$(PYTEST) --cov --cov-report=xml:coverage.xml; status=$$?; \
	  echo "coverage: $$($(PY) -m coverage report --format=total)% of coapkb's lines run by the tests (coverage.xml)"; \
	  exit $$status

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info .coverage .coverage.* coverage.xml
