# psscan: the two commands README.md gives, and their parts.
#   make demo   render the synthetic textile and solve it (no system packages needed)
#   make test   install what the full suite needs, then run every test

CARGO ?= cargo

.PHONY: demo test deps test-rust lint

demo:
	$(CARGO) run --release -- demo

deps:
	./.ci/install-deps

test: deps
	$(MAKE) test-rust

test-rust:
	$(CARGO) test --release

lint:
	$(CARGO) fmt --check
	$(CARGO) clippy --release --all-targets -- -D warnings
