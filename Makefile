# The two commands of the README. Each installs what it needs first (scripts/setup.sh).
SHELL := /bin/bash
.SHELLFLAGS := -euo pipefail -c
.DEFAULT_GOAL := help

# Real data (sequences, the PyDNet++ model) lives beside the checkout, never inside it.
export RELFUSION_DATA ?= $(abspath $(CURDIR)/../shared/data)
DEMO_OUT ?= out/demo
# Mesa's device-select Vulkan layer only reorders adapters (relfusion ranks them itself) and
# prints "XDG_RUNTIME_DIR is invalid" on headless machines: switch it off.
export NODEVICE_SELECT ?= 1

.PHONY: help setup test demo
help:
	@echo "make demo   # set up, build, stream a sequence through relfusiond, fetch the results into $(DEMO_OUT)"
	@echo "make test   # set up and run the whole test suite"

setup:
	@bash scripts/setup.sh >/dev/null

test:
	@env_lines=$$(bash scripts/setup.sh); eval "$$env_lines"; \
	 cargo test --workspace --no-fail-fast

demo:
	@env_lines=$$(bash scripts/setup.sh); eval "$$env_lines"; \
	 cargo build --release -p relfusion-client -p relfusion-server; \
	 DEMO_OUT=$(DEMO_OUT) bash scripts/demo.sh
