# psscan: the two commands README.md gives, and their parts.
#   make demo   render the synthetic textile and solve it (no system packages needed)
#   make test   install what the full suite needs, then run every test
#   make eval   the estimators on the real-data sets in ../shared/data (docs/eval/)

CARGO ?= cargo

.PHONY: demo test deps test-rust test-firmware lint report-screenshots eval bench-e2e

demo:
	$(CARGO) run --release -- demo

deps:
	./.ci/install-deps

test: deps
	$(MAKE) test-firmware
	$(MAKE) test-rust

# The LED firmware: AVR build, native parser tests, a bounded libFuzzer run, and the image
# running in simavr behind a pseudo-terminal.
test-firmware:
	$(MAKE) -C firmware check FUZZ_SECONDS=20

# The second run builds with the libgphoto2 camera backend and OpenCV and runs the tests that
# need them (the rest of the suite does not change with the features). It builds only the
# test binaries that hold such tests (each named opencv_* or gphoto*): linking every other
# test binary against OpenCV again, and compiling the library's own tests a second time, took
# minutes of CI time for no test (tests/layering.rs checks that no test file with such tests
# is missing here, and that no feature-gated module of the library holds unit tests).
FEATURE_TESTS = --test calibration_camera --test calibration_capture \
	--test calibration_e2e --test cli_calibrate --test cli_capture

test-rust:
	$(CARGO) test --release
	$(CARGO) test --release --features "gphoto2 opencv" $(FEATURE_TESTS) -- gphoto opencv

lint:
	$(CARGO) fmt --check
	$(CARGO) clippy --release --all-targets -- -D warnings
	RUSTDOCFLAGS="-D warnings" $(CARGO) doc --no-deps

# Screenshots of report.html for the demo and a DiLiGenT-layout set, into docs/report/.
report-screenshots:
	$(CARGO) build --release
	docs/report/screenshots.sh target/release/psscan

# Real captures with ground truth (DiLiGenT-layout folders under ../shared/data): the table,
# JSON and plot in docs/eval, then the tests that read those sets (ignored by make test).
EVAL_SETS = $(sort $(patsubst %/Normal_gt.mat,%,$(wildcard ../shared/data/*/Normal_gt.mat ../shared/data/*/*/Normal_gt.mat)))

eval:
	@test -n "$(EVAL_SETS)" || { echo "make eval: no set with Normal_gt.mat under ../shared/data"; exit 1; }
	$(CARGO) run --release -- --quiet eval $(EVAL_SETS) --lights 10,20,40,all --estimator ls,adaptive --out docs/eval > /dev/null
	$(CARGO) test --release --test diligent --test batch -- --ignored
	$(CARGO) test --release --lib capture::diligent -- --ignored

# The whole `psscan solve` on 16 MP synthetic DNG and dn16 sets, stage by stage, next to the
# rawpy + NumPy peer (run when $(PYTHON) imports rawpy and numpy). Minutes, a few GiB of disk;
# not part of make test.
PYTHON ?= python3

bench-e2e:
	$(CARGO) build --release
	$(PYTHON) scripts/bench_e2e.py --python $(PYTHON)
