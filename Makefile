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

# Fuzzing (fuzz/): every target for FUZZ_SECONDS, seeds from fuzz/corpus, finds kept in
# fuzz/target/corpus (ignored); a crash stops it and leaves its input in fuzz/artifacts.
FUZZ_SECONDS ?= 60
FUZZ_TARGETS := frame_decode proto_messages archive_extract tum_text tum_list ros2_messages

.PHONY: help setup test test-rerun demo fuzz
help:
	@echo "make demo   # set up, build, stream a sequence through relfusiond, fetch the results into $(DEMO_OUT)"
	@echo "make test   # set up and run the whole test suite"
	@echo "make test-rerun  # the optional rerun recordings (--rerun FILE.rrd) and their test"
	@echo "make fuzz   # fuzz the parsers of untrusted input, FUZZ_SECONDS (default 60) per target"

setup:
	@bash scripts/setup.sh >/dev/null

test:
	@env_lines=$$(bash scripts/setup.sh --test); eval "$$env_lines"; \
	 bash scripts/test.sh

# The client's optional `--rerun` (cargo feature `rerun`) and its test: the rerun SDK and arrow
# would be a third of `make test`'s cold build, so they are built only here.
test-rerun:
	@env_lines=$$(bash scripts/setup.sh --test); eval "$$env_lines"; \
	 cargo test -p relfusion-tests --features rerun --test rerun_recordings

demo:
	@env_lines=$$(bash scripts/setup.sh); eval "$$env_lines"; \
	 cargo build --release -p relfusion-client -p relfusion-server; \
	 DEMO_OUT=$(DEMO_OUT) bash scripts/demo.sh

fuzz:
	@command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz --locked
	@rustup toolchain list | grep -q '^nightly' || rustup toolchain install nightly --profile minimal
	@cd fuzz && for t in $(FUZZ_TARGETS); do \
	   mkdir -p target/corpus/$$t; \
	   echo "fuzz: $$t for $(FUZZ_SECONDS) s"; \
	   cargo +nightly fuzz run -O $$t target/corpus/$$t corpus/$$t -- \
	     -max_total_time=$(FUZZ_SECONDS) -rss_limit_mb=2048 -print_final_stats=1 2>&1 \
	     | grep -E '^(Done|stat::number_of_executed_units|stat::peak_rss_mb)|ERROR|SUMMARY|panicked'; \
	 done
