# The two commands of the README. Both fetch and verify what they need on first use (scripts/setup.py).
.PHONY: setup serve test

ADDR ?= 127.0.0.1:8080

setup:
	python3 scripts/setup.py

serve: setup
	cargo run --release -p libero-agent --features episode-serve -- serve --addr $(ADDR)

test:
	python3 scripts/setup.py --test
	cargo test --workspace --no-fail-fast
