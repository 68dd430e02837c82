# The two commands of the README: `make demo` and `make test`.
SHELL := /bin/bash
.PHONY: setup demo test test-fast bench clean

setup:
	@./tools/setup.sh

demo: setup
	./bike run --record runs

test: setup
	source tools/env.sh && python -m pytest -q

bench: setup
	./bike bench

clean:
	rm -rf build install log .venv
