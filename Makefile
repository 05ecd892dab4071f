# recon — the two commands a new user needs: `make demo` and `make test`.
VENV    ?= .venv
PY      := $(VENV)/bin/python
PIP     := $(PY) -m pip install -q --disable-pip-version-check
RECON   := $(VENV)/bin/recon
STAMP   := $(VENV)/.installed
CORE    := $(VENV)/.core
EXTRAS  := reference,test,batch,render,learned,las,e57,tiles
# the extras recon warmup needs (pillow: recon diff's pictures); the others install meanwhile
WARM_EXTRAS := render
SAMPLE  := sample_data/bunny_scan_000.ply
OUTDIR  := demo_output
PYTEST_ARGS ?=

.PHONY: all install sysdeps viewer warmup demo test test-fast bench lint docs fuzz clean js

all: test

# Open3D links against libusb-1.0 at import; install it when missing (machines run as root).
# `make viewer` needs npm; the tests of `recon view` open its pages in Debian's chromium (headless,
# driven by Playwright).
# recon warmup compiles the ballpivot/mcubes kernels ahead of time with a C compiler: gcc when none is found.
sysdeps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
		echo "installing libusb-1.0-0 (needed by open3d)"; \
		SUDO=""; [ "$$(id -u)" -eq 0 ] || SUDO="sudo"; \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi
	@if ! command -v npm >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then \
		echo "installing npm (make viewer bundles three.js for recon view's pages)"; \
		SUDO=""; [ "$$(id -u)" -eq 0 ] || SUDO="sudo"; \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq nodejs npm >/dev/null; \
	fi
	@if ! command -v chromium >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then \
		echo "installing chromium (the tests of recon view's pages and of 3D Tiles drive it headless)"; \
		SUDO=""; [ "$$(id -u)" -eq 0 ] || SUDO="sudo"; \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq chromium >/dev/null; \
	fi
	@if ! command -v cc >/dev/null 2>&1 && ! command -v gcc >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then \
		echo "installing gcc (recon warmup compiles kernels ahead of time)"; \
		SUDO=""; [ "$$(id -u)" -eq 0 ] || SUDO="sudo"; \
		$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq gcc libc6-dev >/dev/null; \
	fi

# recon alone (numpy, scipy, numba, click, rich): all the demo needs.
$(CORE): pyproject.toml
	@[ -x $(PY) ] || python3 -m venv $(VENV)
	$(PIP) -e .
	@touch $(CORE)

# Everything else: the extras the warm-up needs first; then the other extras install while
# `recon warmup` compiles (pip waits on downloads and the disk, numba on the cores). What is
# installed is pinned (-c), so pip cannot change numba or numpy under the warm-up; should the
# extras need other versions, they are installed after it without the pins, and the warm-up runs
# again.
$(STAMP): $(CORE)
	@$(MAKE) --no-print-directory sysdeps
	$(PIP) -e ".[$(WARM_EXTRAS)]"
	@$(PY) -m pip freeze --exclude-editable > $(VENV)/pins.txt
	@$(PY) tools/extras.py $(EXTRAS) > $(VENV)/extras.txt
	@echo "installing the extras ($(EXTRAS)) while the kernels compile"
	@$(PIP) -r $(VENV)/extras.txt -c $(VENV)/pins.txt > $(VENV)/pip-extras.log 2>&1 & pip=$$!; \
	$(RECON) warmup; warm=$$?; \
	if ! wait $$pip; then \
		tail -n 5 $(VENV)/pip-extras.log; \
		echo "the extras need other versions: installing them, then warming up again"; \
		$(PIP) -e ".[$(EXTRAS)]" && $(RECON) warmup || exit 1; \
	elif [ $$warm -ne 0 ]; then exit $$warm; fi
	@touch $(STAMP)

# three.js for `recon view`'s pages: the versions pinned in tools/viewer/package-lock.json, bundled
# by esbuild into one script that every page inlines (package data; git ignores it)
VIEWER_JS  := recon_cli/eval/viewer/three.min.js
VIEWER_NPM := tools/viewer
$(VIEWER_JS): $(VIEWER_NPM)/package.json $(VIEWER_NPM)/package-lock.json $(VIEWER_NPM)/three-entry.js
	@$(MAKE) --no-print-directory sysdeps
	npm ci --prefix $(VIEWER_NPM) --no-audit --no-fund --loglevel=error
	$(VIEWER_NPM)/node_modules/.bin/esbuild $(VIEWER_NPM)/three-entry.js --bundle --minify \
		--format=iife --global-name=RECON3 --target=es2020 --log-level=warning \
		--banner:js="/*! three.js $$(node -p 'require("./$(VIEWER_NPM)/node_modules/three/package.json").version') (npm), bundled by esbuild for recon view */" \
		--outfile=$@.tmp && mv $@.tmp $@

viewer: $(VIEWER_JS)

# the checkers the tests run on the glTF and 3D Tiles files recon writes (the Khronos glTF-Validator;
# three.js and 3d-tiles-renderer, loaded in chromium), pinned by tools/gltf/package-lock.json into
# tools/gltf/node_modules (not committed)
JS_STAMP := tools/gltf/node_modules/.installed
$(JS_STAMP): tools/gltf/package.json tools/gltf/package-lock.json
	@$(MAKE) --no-print-directory sysdeps
	npm ci --prefix tools/gltf --no-audit --no-fund --loglevel=error
	@touch $(JS_STAMP)

js: $(JS_STAMP)

install: $(STAMP) $(VIEWER_JS) $(JS_STAMP)

# compile every numba kernel into the per-user cache (make install does it once; again after editing a kernel)
warmup: $(STAMP)
	$(RECON) warmup

# The demo needs recon alone, and compiles only its own kernels as it runs (about a minute of one
# core, once); `make install` adds every extra and compiles every command's kernels.
demo: $(CORE)
	@mkdir -p $(OUTDIR)
	@[ -f $(STAMP) ] || echo "first run: numba compiles the demo's kernels (once; \`make install\` compiles every command's)"
	$(RECON) run pipelines/demo.toml $(SAMPLE) $(OUTDIR)/bunny_scan_000_poisson.ply
	@echo "result written to $(OUTDIR)/bunny_scan_000_poisson.ply"
	$(RECON) info $(OUTDIR)/bunny_scan_000_poisson.ply

# worksteal: each worker starts on a contiguous half (a file's cached meshes stay on one worker)
# and takes the other's queue when idle (no worker waits out the other's long tests)
test: sysdeps $(STAMP) $(VIEWER_JS) $(JS_STAMP)
	$(PY) -m pytest -n 2 --dist worksteal $(PYTEST_ARGS)

test-fast: sysdeps $(STAMP) $(VIEWER_JS) $(JS_STAMP)
	$(PY) -m pytest -n 2 --dist worksteal -m "not slow and not fuzz" $(PYTEST_ARGS)

# the long fuzzing runs (tests marked fuzz: hundreds of generated files per reader, every option
# of the stages), left out of make test
fuzz: sysdeps $(STAMP) $(VIEWER_JS) $(JS_STAMP)
	$(PY) -m pytest -n 2 --dist worksteal -m fuzz $(PYTEST_ARGS)

bench: sysdeps $(STAMP) $(VIEWER_JS) $(JS_STAMP)
	$(PY) bench/run_bench.py --out bench/results.md

# ruff (format and lint) and mypy, configured in pyproject.toml; the `lint` extra holds them
LINT_STAMP := $(VENV)/.lint-installed
$(LINT_STAMP): pyproject.toml $(STAMP)
	$(PY) -m pip install -q --disable-pip-version-check -e ".[lint]"
	@touch $(LINT_STAMP)

lint: $(LINT_STAMP)
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/ruff check .
	$(PY) -m mypy

# Sphinx with warnings as errors and nitpicky cross-references; the `docs` extra holds it
DOCS_STAMP := $(VENV)/.docs-installed
$(DOCS_STAMP): pyproject.toml $(STAMP)
	$(PY) -m pip install -q --disable-pip-version-check -e ".[docs]"
	@touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	$(PY) -m sphinx -W -n --keep-going -q -b html docs docs/_build/html
	@echo "docs written to docs/_build/html/index.html"

clean:
	rm -rf $(VENV) $(OUTDIR) $(VIEWER_JS) $(VIEWER_NPM)/node_modules .pytest_cache .mypy_cache .ruff_cache docs/_build docs/stages docs/cli docs/_generated build *.egg-info
