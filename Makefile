# The two commands of the README. Both fetch and verify what they need on first use (scripts/setup.py).
.PHONY: setup serve test

ADDR ?= 127.0.0.1:8080

setup:
	python3 scripts/setup.py

serve: setup
	cargo run --release -p libero-agent --features episode-serve -- serve --addr $(ADDR)

# Every feature combination the manifests offer compiles too (the offline toolkit without `episode-serve`, the
# protocol core without `world`): only `cargo check`, since each is its own dependency graph (about 1 min).
test:
	python3 scripts/setup.py --test
	cargo check --quiet -p libero-agent -p libero-episode -p libero-store --no-default-features
	cargo test --workspace --no-fail-fast
