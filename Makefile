# The two commands of the README. Both fetch and verify what they need on first use (scripts/setup.py).
.PHONY: setup serve test

ADDR ?= 127.0.0.1:8080

setup:
	python3 scripts/setup.py

serve: setup
	cargo run --release -p libero-agent --features episode-serve -- serve --addr $(ADDR)

# Every feature combination the manifests offer compiles too (the offline toolkit without `episode-serve`, the
# protocol core without `world`): only `cargo check`, since each is its own dependency graph (about 1 min).
# The tests run under cargo-nextest where it is installed (each test a process, two at a time across all test
# binaries: .config/nextest.toml), which is about a quarter faster on 2 cores; else under `cargo test`.
test:
	python3 scripts/setup.py --test
	cargo check --quiet -p libero-agent -p libero-episode -p libero-store --no-default-features
	@if cargo nextest --version >/dev/null 2>&1; then \
		cargo nextest run --workspace --no-fail-fast; \
	else \
		echo "cargo-nextest not installed (cargo install cargo-nextest --locked): running cargo test"; \
		cargo test --workspace --no-fail-fast; \
	fi
