# The two commands of the README: `make demo` and `make test`.
SHELL := /bin/bash
.PHONY: setup demo test test-faults test-smoke bench peers clean

setup:
	@./tools/setup.sh

demo: setup
	./bike run --record runs

# --durations: the slowest tests in every log (the suite's aim is under 15 minutes on 2 cores)
test: setup
	source tools/env.sh && python -m pytest -q --durations=30

# only the reliability suite's process-level fault tests (kill -9, message loss / delay; part
# of `make test` too)
test-faults: setup
	source tools/env.sh && python -m pytest -q -m faults

# a short process-level smoke (launcher and Ctrl-C, kill -9 of each node under `bike run`, the
# session following a plant's clock back, the recorded demo graph, the kernels' warm-up): CI
# runs it on the other supported interpreter, Python 3.12. The restart and give-up fault tests
# exercise the same interpreter paths and run in the 3.11 suite (`make test`)
test-smoke: setup
	source tools/env.sh && python -m pytest -q test/test_launcher.py test/test_graph.py test/test_warm_up.py \
		test/test_faults_kill.py::test_kill_9_under_bike_run_ends_the_run_cleanly \
		test/test_faults_kill.py::test_session_follows_the_clock_back_with_one_warning

bench: setup
	./bike bench

# optional benchmark peers (motulator 0.18 on Python 3.12, gym-electric-motor 3.0), each in its
# own venv under $(BIKE_PEERS_DIR) (default ~/.cache/bike-peers), never in the project's venv
peers:
	@./tools/peers/setup.sh

clean:
	rm -rf build install log .venv
