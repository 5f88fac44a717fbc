# Two entry points, both safe on a fresh Debian/Ubuntu machine with Python 3.11:
#   make app   - set up, build the demo session if it is missing, serve the app on http://127.0.0.1:8080
#   make test  - set up, run the whole test suite (lint, docs build, unit, Ray and headless-browser tests)
SHELL := /bin/bash
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
HOST ?= 127.0.0.1
PORT ?= 8080
APT_GET := DEBIAN_FRONTEND=noninteractive apt-get
IS_ROOT := $(shell [ "$$(id -u)" = 0 ] && echo yes)

.PHONY: app test test-ray test-fast lint docs bench report screenshots demo corpus corpus50 default-model paper-model sysdeps browserdeps clean

app: $(STAMP) demo
	$(BIN)/factorydet app --session demo --host $(HOST) --port $(PORT)

demo: $(STAMP)
	$(BIN)/factorydet demo --session demo

# The docs build is not --quiet: that hides the warnings --strict turns into failures.
# The suite on every core this process may use (pytest-xdist; TEST_WORKERS=0 runs it in this
# process), then the browser tests one at a time (each drives a headless Chromium whose software
# WebGL takes a core of its own), then the Ray tier.
TEST_WORKERS ?= $(shell nproc)
test: $(STAMP) browserdeps lint
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir $$(mktemp -d)
	$(BIN)/python -m pytest -m "not ray and not browser" -n $(TEST_WORKERS) --maxprocesses 4 --dist worksteal \
	  --durations=25
	$(BIN)/python -m pytest -m "browser and not ray" --durations=10
	$(MAKE) --no-print-directory test-ray

# The tests that start Ray (a local one, a two-node cluster), in a network namespace with only
# loopback so that Ray's ports are never open to the network (needs root or user namespaces).
test-ray: $(STAMP)
	$(BIN)/python -m factorydet_core.scale.netns -- $(BIN)/python -m pytest -m ray

# The quick loop while editing: lint, the import contract and every test not marked slow or browser.
test-fast: $(STAMP) lint
	$(BIN)/python -m pytest -m "not slow and not browser" -n $(TEST_WORKERS) --maxprocesses 4 -q

# The documentation site (README's links, docs/*.md) into site/; strict: a broken link fails.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

# ruff, and the layering contracts of pyproject.toml's [tool.importlinter] (import-linter).
lint: $(STAMP)
	$(BIN)/ruff check factorydet_core app tests
	$(BIN)/lint-imports --no-cache

# Re-runs every benchmark: records under docs/bench/, tables into docs/benchmarks.md, docs/labelling.md and the README (an hour or more).
BENCH_DATA ?= /tmp/bench_sim
SCALE_DATA ?= /tmp/factorydet_paper_scale
REAL := ../shared/data/real
bench: $(STAMP) browserdeps corpus corpus50
	$(BIN)/factorydet bench simulate --readme docs/benchmarks.md
	rm -rf $(BENCH_DATA) && $(BIN)/factorydet simulate --out $(BENCH_DATA) --frames 24 --seed 0
	$(BIN)/factorydet bench pipeline $(BENCH_DATA) --frames 8 --json --readme docs/benchmarks.md
	$(BIN)/factorydet bench pipeline $(CORPUS) --frames 20 --json --readme docs/benchmarks.md --readme-block pipeline-corpus
	$(BIN)/factorydet bench pipeline $(REAL)/scannet_scene0000_00.npz $(REAL)/scannet_scene0000_01.npz \
	  $(REAL)/scannet_scene0000_02.npz --json --readme docs/benchmarks.md
	$(BIN)/factorydet bench sweep $(BENCH_DATA) --frames 4 --png docs/voxel_sweep.png --readme docs/benchmarks.md
	$(BIN)/factorydet bench classifier $(BENCH_DATA) --widths 0.0625,1.0 --features aggregated,direct \
	  --epochs 15 --max-fit-seconds 240 --train-frames 4 --frames 2 --readme docs/benchmarks.md
	$(BIN)/factorydet demo
	$(BIN)/factorydet bench detect sessions/demo/data --model default --frames 4 --repeats 2 \
	  --compare-set screen_trees=0 --busy --heldout --readme docs/performance.md
	$(BIN)/factorydet bench memory --sizes 1000000,5000000 --readme docs/performance.md
	# One more mining round of the shipped model's session (made by make default-model), as it ran
	# before thresholds were tuned out of fold by default.
	$(BIN)/factorydet bench mining --session corpus-head --round-epochs 5 --heldout --readme docs/performance.md \
	  --threshold-folds 0 --threshold-objective class
	# What the app's Train does on the demo session: a full retrain, then a next round (the first two
	# with the thresholds tuned on the fitted frames, as before out-of-fold thresholds were the default).
	$(BIN)/factorydet bench mining --session demo --full-run --before-after --round-epochs 5 \
	  --threshold-folds 0 --threshold-objective class --readme docs/performance.md --readme-block mining-demo
	$(BIN)/factorydet bench mining --session demo --full-run --before-after --round-epochs 5 --verdicts 20 \
	  --threshold-folds 0 --threshold-objective class --refit-row-share 1 --readme docs/performance.md \
	  --readme-block mining-demo-reviewed
	# The same with the default threshold folds (the fold models going on every next round), both refitting
	# the regressor on all its rows, as they ran before a next round's refit took half of them.
	$(BIN)/factorydet bench mining --session demo --full-run --before-after --round-epochs 5 --verdicts 20 \
	  --threshold-folds 2 --threshold-objective total --refit-row-share 1 --readme docs/performance.md \
	  --readme-block mining-demo-reviewed-folds
	# A reviewer's next round refitting the box quality regressor on half the option rows (the default)
	# and on all of them, three training seeds each, going on from one full run of a copy of the demo
	# session; the models measured on held-out factories no setting was chosen on.
	rm -rf /tmp/factorydet_refit && mkdir -p /tmp/factorydet_refit && cp -r sessions/demo /tmp/factorydet_refit/demo
	$(BIN)/factorydet train --session demo --root /tmp/factorydet_refit --mode full
	$(BIN)/factorydet bench mining --session demo --root /tmp/factorydet_refit --before-after --round-epochs 5 \
	  --verdicts 20 --seeds 0,1,2 --compare-set refit_row_share=1.0 --heldout --heldout-seeds 121,122,123,124,125,126 \
	  --readme docs/performance.md --readme-block mining-demo-refit-rows
	$(BIN)/factorydet bench quality $(CORPUS) --model paper --seeds 0,1,2 --heldout-seeds 101,102,103 \
	  --heldout-frames 12 --epochs 20 --rounds 1 --out docs/bench/quality.json --readme README.md
	$(BIN)/factorydet bench fuzz --cases 1000 --seed 0 --out docs/bench/fuzz.json
	$(BIN)/factorydet bench import --boxes 10000 --out docs/bench/label_import.json
	$(BIN)/factorydet bench import --boxes 10000 --large-box --out docs/bench/label_import_large_box.json
	$(BIN)/python -m app.walkthrough sessions/demo/data --repeats 5 --readme docs/labelling.md
	# The same with Object verdicts among the review's (label once writes each into every frame showing it).
	$(BIN)/python -m app.walkthrough sessions/demo/data --repeats 5 --verdict-keys bobxo --readme docs/labelling.md \
	  --readme-block walkthrough-object-verdicts --out docs/bench/walkthrough-object-verdicts.json
	# The edits alone, with every point drawn and with at most 20,000 (Display's Points drawn).
	$(BIN)/python -m app.walkthrough sessions/demo/data --repeats 5 --no-retrain --readme docs/labelling.md \
	  --readme-block walkthrough-edits-points-all
	$(BIN)/python -m app.walkthrough sessions/demo/data --repeats 5 --no-retrain --points-drawn 20000 \
	  --readme docs/labelling.md --readme-block walkthrough-edits-points-20k
	# The edits alone again, first timing a render with viser's default shadows (off in the app) on and off.
	$(BIN)/python -m app.walkthrough sessions/demo/data --repeats 5 --no-retrain --shadow-cost \
	  --readme docs/labelling.md --readme-block walkthrough-edits-no-shadows \
	  --out docs/bench/walkthrough-edits-no-shadows.json
	# ... and with the lightest scene the Display panel gives (20,000 points drawn, no floor grid).
	$(BIN)/python -m app.walkthrough sessions/demo/data --repeats 5 --no-retrain --points-drawn 20000 --no-grid \
	  --readme docs/labelling.md --readme-block walkthrough-edits-points-20k-no-grid \
	  --out docs/bench/walkthrough-edits-points-20k-no-grid.json
	# The edits timed in the page's own clock too, with the app's defaults and with the lightest scene.
	$(BIN)/python -m app.walkthrough sessions/demo/data --repeats 5 --no-retrain \
	  --readme docs/labelling.md --readme-block walkthrough-edits-page-clock \
	  --out docs/bench/walkthrough-edits-page-clock.json
	$(BIN)/python -m app.walkthrough sessions/demo/data --repeats 5 --no-retrain --points-drawn 20000 --no-grid \
	  --readme docs/labelling.md --readme-block walkthrough-edits-page-clock-20k-no-grid \
	  --out docs/bench/walkthrough-edits-page-clock-20k-no-grid.json
	$(BIN)/python -m app.walkthrough sessions/demo/data --repeats 5 --no-retrain --settle-ms 300 \
	  --readme docs/labelling.md --readme-block walkthrough-edits-page-clock-settled \
	  --out docs/bench/walkthrough-edits-page-clock-settled.json
	# The whole walkthrough (edits, Object verdicts, both retrains) in the page's clock.
	$(BIN)/python -m app.walkthrough sessions/demo/data --repeats 5 --verdict-keys bobxo \
	  --readme docs/labelling.md --readme-block walkthrough-page-clock --out docs/bench/walkthrough-page-clock.json
	$(BIN)/factorydet bench world-labels --heldout-seeds 201,202,203 --heldout-frames 12 --readme docs/labelling.md \
	  --readme-block world-labels-validation
	$(BIN)/factorydet bench world-labels --heldout-seeds 101,102,103 --heldout-frames 12 --readme docs/labelling.md
	$(BIN)/factorydet bench world-labels --heldout-seeds 104,105,106 --heldout-frames 60 --readme docs/labelling.md \
	  --readme-block world-labels-long
	# The labelling loop. Lines of records made before thresholds were tuned out of fold by default name
	# --threshold-folds 0 --threshold-objective class, as those records ran.
	# Every line trains on every label a person made (the default), except the two
	# sparse-label lines, which leave out a person's labels holding fewer than half the policy's points
	# (--label-min-points -1).
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 50,200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --model-box-targets --out docs/bench/hitl.json --readme docs/review-loop.md \
	  --review-order score --no-refit-box-quality \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 50,200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --model-box-targets --out docs/bench/hitl-50.json --readme docs/review-loop.md \
	  --readme-block hitl-50 --review-order score --no-refit-box-quality \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 50,200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --variants blind_safe,full --hold-places \
	  --out docs/bench/hitl-safe.json --readme docs/review-loop.md --readme-block hitl-safe --no-refit-box-quality \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 50,200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --review-order score \
	  --variants reviewed_50,reviewed_200,full --model-box-targets --out docs/bench/hitl-50-place.json --readme docs/review-loop.md \
	  --readme-block hitl-50-place --no-refit-box-quality --resume \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 50,200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --variants full_late,full \
	  --out docs/bench/hitl-50-late.json --readme docs/review-loop.md --readme-block hitl-50-late --no-refit-box-quality --resume \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 50,200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class --review-order class \
	  --variants reviewed_50,reviewed_200,full --model-box-targets --out docs/bench/hitl-50-class.json --readme docs/review-loop.md \
	  --readme-block hitl-50-class --no-refit-box-quality --resume \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-class.json docs/bench/hitl-50-place.json \
	  --readme docs/review-loop.md --readme-block hitl-50-class-vs-place
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class --review-order class \
	  --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-50-refit.json --readme docs/review-loop.md \
	  --readme-block hitl-50-refit --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-refit.json docs/bench/hitl-50-class.json \
	  --readme docs/review-loop.md --readme-block hitl-50-refit-vs-class
	# blind_safe with the refit: a copy of the refit record gives blind and full (--resume takes the
	# runs that holding negatives does not touch), so only blind_safe trains.
	test -f docs/bench/hitl-50-safe-refit.json || cp docs/bench/hitl-50-refit.json docs/bench/hitl-50-safe-refit.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --variants blind_safe,full --hold-places --out docs/bench/hitl-50-safe-refit.json \
	  --readme docs/review-loop.md --readme-block hitl-50-safe-refit --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# The refit boosting the model's regressor on with 100 trees instead (blind and full from the refit record).
	test -f docs/bench/hitl-50-refit100.json || cp docs/bench/hitl-50-refit.json docs/bench/hitl-50-refit100.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class --review-order class \
	  --refit-trees 100 --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-50-refit100.json \
	  --readme docs/review-loop.md --readme-block hitl-50-refit100 --resume \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-refit100.json docs/bench/hitl-50-refit.json \
	  --readme docs/review-loop.md --readme-block hitl-50-refit100-vs-refit
	# blind_safe also recalibrating the background (blind and full from the refit record), against
	# blind_safe holding alone.
	test -f docs/bench/hitl-50-safe-recal.json || cp docs/bench/hitl-50-refit.json docs/bench/hitl-50-safe-recal.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --variants blind_safe,full --hold-places --recalibrate-background 0.5 --out docs/bench/hitl-50-safe-recal.json \
	  --readme docs/review-loop.md --readme-block hitl-50-safe-recal --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-safe-recal.json docs/bench/hitl-50-safe-refit.json \
	  --readme docs/review-loop.md --readme-block hitl-50-safe-recal-vs-hold
	# The loop's headline figures: the same models measured on held-out factories, 30% unannotated.
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants full --out docs/bench/hitl-heldout.json \
	  --readme docs/review-loop.md --readme-block hitl-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# blind_safe recalibrating there too (blind and full from the held-out record).
	test -f docs/bench/hitl-safe-recal-heldout.json || cp docs/bench/hitl-heldout.json docs/bench/hitl-safe-recal-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants blind_safe,full --hold-places \
	  --recalibrate-background 0.5 --out docs/bench/hitl-safe-recal-heldout.json \
	  --readme docs/review-loop.md --readme-block hitl-safe-recal-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# ... recalibrating by class (each class's bar: the median of its labelled sets).
	test -f docs/bench/hitl-safe-byclass-heldout.json || cp docs/bench/hitl-heldout.json docs/bench/hitl-safe-byclass-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants blind_safe,full --hold-places \
	  --recalibrate-background 0.5 --recalibrate-by-class --out docs/bench/hitl-safe-byclass-heldout.json \
	  --readme docs/review-loop.md --readme-block hitl-safe-byclass-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# A reviewer answering 200 places per round, on the same held-out factories.
	test -f docs/bench/hitl-reviewed-heldout.json || cp docs/bench/hitl-heldout.json docs/bench/hitl-reviewed-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class --review-order class \
	  --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants reviewed_200,full \
	  --model-box-targets --out docs/bench/hitl-reviewed-heldout.json --readme docs/review-loop.md --readme-block hitl-reviewed-heldout \
	  --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# The same reviewer holding what it leaves, as blind_safe (the rest from the reviewed record).
	test -f docs/bench/hitl-reviewed-safe-heldout.json || cp docs/bench/hitl-reviewed-heldout.json docs/bench/hitl-reviewed-safe-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class --review-order class \
	  --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants reviewed_200,reviewed_safe_200,full \
	  --hold-places --recalibrate-background 0.5 --recalibrate-by-class \
	  --model-box-targets --out docs/bench/hitl-reviewed-safe-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-reviewed-safe-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-reviewed-safe-heldout.json --variants reviewed_safe_200,reviewed_200 \
	  --readme docs/review-loop.md --readme-block hitl-reviewed-safe-vs-reviewed-heldout
	# Blind mining and full labels on the same held-out factories, 50% unannotated.
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants full --out docs/bench/hitl-50-heldout.json \
	  --readme docs/review-loop.md --readme-block hitl-50-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# ... and a reviewer answering 200 places a round there.
	test -f docs/bench/hitl-50-reviewed-heldout.json || cp docs/bench/hitl-50-heldout.json docs/bench/hitl-50-reviewed-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class --review-order class \
	  --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants reviewed_200,full \
	  --model-box-targets --out docs/bench/hitl-50-reviewed-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-50-reviewed-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# ... the same reviewer holding what it leaves (the rest from the reviewed record).
	test -f docs/bench/hitl-50-reviewed-safe-heldout.json || cp docs/bench/hitl-50-reviewed-heldout.json docs/bench/hitl-50-reviewed-safe-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class --review-order class \
	  --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants reviewed_200,reviewed_safe_200,full \
	  --hold-places --recalibrate-background 0.5 --recalibrate-by-class \
	  --model-box-targets --out docs/bench/hitl-50-reviewed-safe-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-50-reviewed-safe-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-reviewed-safe-heldout.json --variants reviewed_safe_200,reviewed_200 \
	  --readme docs/review-loop.md --readme-block hitl-50-reviewed-safe-vs-reviewed-heldout
	# The reviewer's queue most likely an object first, the cut still by class turns (30% and 50%).
	test -f docs/bench/hitl-review-score-heldout.json || cp docs/bench/hitl-reviewed-heldout.json docs/bench/hitl-review-score-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order score --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants reviewed_200,full \
	  --model-box-targets --out docs/bench/hitl-review-score-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-review-score-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-review-score-heldout.json docs/bench/hitl-reviewed-heldout.json \
	  --readme docs/review-loop.md --readme-block hitl-review-score-vs-turns-heldout
	test -f docs/bench/hitl-50-review-score-heldout.json || cp docs/bench/hitl-50-reviewed-heldout.json docs/bench/hitl-50-review-score-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order score --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants reviewed_200,full \
	  --model-box-targets --out docs/bench/hitl-50-review-score-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-50-review-score-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-review-score-heldout.json docs/bench/hitl-50-reviewed-heldout.json \
	  --readme docs/review-loop.md --readme-block hitl-50-review-score-vs-turns-heldout
	# The reviewer's queue also holding every false positive after the mined ones, for review alone (50% and 30%).
	test -f docs/bench/hitl-50-review-extra-heldout.json || cp docs/bench/hitl-50-reviewed-heldout.json docs/bench/hitl-50-review-extra-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class --review-order class \
	  --review-extra -1 --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants reviewed_200,full \
	  --model-box-targets --out docs/bench/hitl-50-review-extra-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-50-review-extra-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-review-extra-heldout.json docs/bench/hitl-50-reviewed-heldout.json \
	  --readme docs/review-loop.md --readme-block hitl-50-review-extra-vs-reviewed-heldout
	test -f docs/bench/hitl-review-extra-heldout.json || cp docs/bench/hitl-reviewed-heldout.json docs/bench/hitl-review-extra-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class --review-order class \
	  --review-extra -1 --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants reviewed_200,full \
	  --model-box-targets --out docs/bench/hitl-review-extra-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-review-extra-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-review-extra-heldout.json docs/bench/hitl-reviewed-heldout.json \
	  --readme docs/review-loop.md --readme-block hitl-review-extra-vs-reviewed-heldout
	# blind_safe recalibrating by class at 50% unannotated.
	test -f docs/bench/hitl-50-safe-byclass-heldout.json || cp docs/bench/hitl-50-heldout.json docs/bench/hitl-50-safe-byclass-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants blind_safe,full --hold-places \
	  --recalibrate-background 0.5 --recalibrate-by-class --out docs/bench/hitl-50-safe-byclass-heldout.json \
	  --readme docs/review-loop.md --readme-block hitl-50-safe-byclass-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# The reviewer's places in an order learned from its own verdicts (50% and 30%).
	test -f docs/bench/hitl-50-review-learned-heldout.json || cp docs/bench/hitl-50-reviewed-heldout.json docs/bench/hitl-50-review-learned-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order learned --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants reviewed_200,full \
	  --model-box-targets --out docs/bench/hitl-50-review-learned-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-50-review-learned-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-review-learned-heldout.json docs/bench/hitl-50-reviewed-heldout.json \
	  --readme docs/review-loop.md --readme-block hitl-50-review-learned-vs-reviewed-heldout
	test -f docs/bench/hitl-review-learned-heldout.json || cp docs/bench/hitl-reviewed-heldout.json docs/bench/hitl-review-learned-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order learned --heldout --heldout-seeds 101,102,103 --heldout-frames 12 --variants reviewed_200,full \
	  --model-box-targets --out docs/bench/hitl-review-learned-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-review-learned-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-review-learned-heldout.json docs/bench/hitl-reviewed-heldout.json \
	  --readme docs/review-loop.md --readme-block hitl-review-learned-vs-reviewed-heldout
	# The learned order's reviewer holding what it leaves, as blind_safe (50% and 30%; the rest from the learned records).
	test -f docs/bench/hitl-50-review-learned-safe-heldout.json || cp docs/bench/hitl-50-review-learned-heldout.json docs/bench/hitl-50-review-learned-safe-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order learned --heldout --heldout-seeds 101,102,103 --heldout-frames 12 \
	  --variants reviewed_200,reviewed_safe_200,full --hold-places --recalibrate-background 0.5 --recalibrate-by-class \
	  --model-box-targets --out docs/bench/hitl-50-review-learned-safe-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-50-review-learned-safe-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-review-learned-safe-heldout.json \
	  --variants reviewed_safe_200,reviewed_200 --readme docs/review-loop.md \
	  --readme-block hitl-50-review-learned-safe-vs-learned-heldout
	test -f docs/bench/hitl-review-learned-safe-heldout.json || cp docs/bench/hitl-review-learned-heldout.json docs/bench/hitl-review-learned-safe-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order learned --heldout --heldout-seeds 101,102,103 --heldout-frames 12 \
	  --variants reviewed_200,reviewed_safe_200,full --hold-places --recalibrate-background 0.5 --recalibrate-by-class \
	  --model-box-targets --out docs/bench/hitl-review-learned-safe-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-review-learned-safe-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-review-learned-safe-heldout.json \
	  --variants reviewed_safe_200,reviewed_200 --readme docs/review-loop.md \
	  --readme-block hitl-review-learned-safe-vs-learned-heldout
	# The learned order's reviewer over a longer queue: every false positive of the last mining
	# after the mined ones, for review alone (30% and 50%; blind and full from the learned records).
	test -f docs/bench/hitl-review-learned-extra-heldout.json || cp docs/bench/hitl-review-learned-heldout.json docs/bench/hitl-review-learned-extra-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103 --heldout-frames 12 \
	  --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-review-learned-extra-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-review-learned-extra-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-review-learned-extra-heldout.json \
	  docs/bench/hitl-review-learned-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-review-learned-extra-vs-learned-heldout
	test -f docs/bench/hitl-50-review-learned-extra-heldout.json || cp docs/bench/hitl-50-review-learned-heldout.json docs/bench/hitl-50-review-learned-extra-heldout.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103 --heldout-frames 12 \
	  --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-50-review-learned-extra-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-50-review-learned-extra-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-review-learned-extra-heldout.json \
	  docs/bench/hitl-50-review-learned-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-50-review-learned-extra-vs-learned-heldout
	# The learned order over the longer queue (chosen on factories 101-103) on three held-out
	# factories no record had seen (104-106), 30%; then the same reviewer looking where a sparse
	# place is seen best (blind and full from that record).
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 104,105,106 --heldout-frames 12 \
	  --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-review-learned-extra-unseen.json --readme docs/review-loop.md \
	  --readme-block hitl-review-learned-extra-unseen --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	test -f docs/bench/hitl-review-best-view-unseen.json || cp docs/bench/hitl-review-learned-extra-unseen.json docs/bench/hitl-review-best-view-unseen.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --review-best-view --heldout --heldout-seeds 104,105,106 \
	  --heldout-frames 12 --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-review-best-view-unseen.json \
	  --readme docs/review-loop.md --readme-block hitl-review-best-view-unseen --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-review-best-view-unseen.json \
	  docs/bench/hitl-review-learned-extra-unseen.json --readme docs/review-loop.md \
	  --readme-block hitl-review-best-view-vs-learned-extra-unseen
	# The same reviewer (50 and 200 places a round), blind mining and full labels on all six held-out
	# factories (101-106), every detector trained by one version of the library: the loop's headline.
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 50,200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants reviewed_50,reviewed_200,full --model-box-targets --out docs/bench/hitl-review-learned-extra-six.json \
	  --readme docs/review-loop.md --readme-block hitl-review-learned-extra-six --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# Five more training seeds (5-9) of blind mining, the reviewer's 200 places a round and full labels on
	# the six held-out factories, seeds 0-4 read back from the record above: ten seeds in all.
	test -f docs/bench/hitl-review-learned-extra-ten-seeds.json || cp docs/bench/hitl-review-learned-extra-six.json docs/bench/hitl-review-learned-extra-ten-seeds.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5,6,7,8,9 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-review-learned-extra-ten-seeds.json \
	  --readme docs/review-loop.md --readme-block hitl-review-learned-extra-ten-seeds --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# One operating threshold for every class (--no-class-thresholds), blind mining and full labels on
	# the six held-out factories, three seeds: do the per-class thresholds cost people their precision?
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --no-class-thresholds --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants full --out docs/bench/hitl-no-class-thresholds-six.json \
	  --readme docs/review-loop.md --readme-block hitl-no-class-thresholds-six --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# The first fit at the product's 20 epochs (LoopSettings.epochs; the records above fit 5), each round
	# after it 5 as before: blind mining, the reviewer's 200 places a round and full labels, seeds 0-5.
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-review-learned-extra-e20-six.json \
	  --readme docs/review-loop.md --readme-block hitl-review-learned-extra-e20-six --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# The reviewer at 30% with label once's settled poses and its Object labels teaching their class
	# alone (today's defaults; blind and full read back from the record above), seeds 0-5; then against
	# the reviewer above (the drifting poses, the mined boxes learnt), seed by seed.
	test -f docs/bench/hitl-e20-class-alone-six.json || cp docs/bench/hitl-review-learned-extra-e20-six.json docs/bench/hitl-e20-class-alone-six.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants reviewed_200,full --out docs/bench/hitl-e20-class-alone-six.json \
	  --readme docs/review-loop.md --readme-block hitl-e20-class-alone-six --resume --refit-row-share 1 --resume-other-library \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-e20-class-alone-six.json \
	  docs/bench/hitl-review-learned-extra-e20-six.json --readme docs/review-loop.md \
	  --readme-block hitl-e20-class-alone-vs-drift-six
	# Twice the training frames (16) at 30%, blind mining and full labels: does the gap open with more
	# data? (Runs of one library version, read back whatever the code is now.)
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 16 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind,full --out docs/bench/hitl-e20-16frames-five.json \
	  --readme docs/review-loop.md --readme-block hitl-e20-16frames-five --resume --refit-row-share 1 --resume-other-library \
	  --threshold-folds 0 --threshold-objective class
	# Half the objects unannotated and the first fit at 20 epochs: blind mining, the reviewer's 200 places
	# a round and full labels, seeds 0-5.
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-50-e20-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-six --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# The reviewer at 50% once label once registers the frames with the settled calibration at the
	# odometry's height (blind and full, which do not carry labels between frames, read back from the
	# record above), seeds 0-5; then the reviewer against the one above, seed by seed.
	test -f docs/bench/hitl-50-e20-world-six.json || cp docs/bench/hitl-50-e20-six.json docs/bench/hitl-50-e20-world-six.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-50-e20-world-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-world-six --resume --refit-row-share 1 --resume-other-library \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-e20-world-six.json docs/bench/hitl-50-e20-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-world-vs-drift-six
	# The reviewer at 50% with its Object verdicts' labels (the mined boxes) teaching their class alone
	# (the default since; the lines above keep --model-box-targets, as they ran; blind and full, which
	# have no verdicts, read back), 50 and 200 places a round, seeds 0-5; then against the reviewer
	# above, seed by seed.
	test -f docs/bench/hitl-50-e20-class-alone-six.json || cp docs/bench/hitl-50-e20-world-six.json docs/bench/hitl-50-e20-class-alone-six.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 50,200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants reviewed_50,reviewed_200,full \
	  --out docs/bench/hitl-50-e20-class-alone-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-class-alone-six --resume --refit-row-share 1 --resume-other-library \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-e20-class-alone-six.json docs/bench/hitl-50-e20-world-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-class-alone-vs-world-six
	# blind_safe at 50% with the first fit at 20 epochs, holding places and recalibrating the background
	# (blind and full read back from the record above), seeds 0-3.
	test -f docs/bench/hitl-50-e20-safe-recal-six.json || cp docs/bench/hitl-50-e20-six.json docs/bench/hitl-50-e20-safe-recal-six.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind_safe,full --hold-places --recalibrate-background 0.5 \
	  --out docs/bench/hitl-50-e20-safe-recal-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-safe-recal-six --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	# blind_safe with pseudo-labels: the negatives scoring 0.6 or more, off the labels, teach their
	# predicted class until reviewed, those between 0.35 and 0.6 are held (blind and full read back from
	# hitl-50-e20-six), seeds 0-5; then against blind_safe holding alone, seed by seed.
	test -f docs/bench/hitl-50-e20-safe-pseudo-six.json || cp docs/bench/hitl-50-e20-six.json docs/bench/hitl-50-e20-safe-pseudo-six.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind_safe,full --hold-places --recalibrate-background 0.5 \
	  --pseudo-label-confident 0.6 --out docs/bench/hitl-50-e20-safe-pseudo-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-safe-pseudo-six --resume --refit-row-share 1 --resume-other-library \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-e20-safe-pseudo-six.json \
	  docs/bench/hitl-50-e20-safe-recal-six.json --readme docs/review-loop.md \
	  --readme-block hitl-50-e20-safe-pseudo-vs-recal-six
	# ... with each pseudo-label of an object that stands still carried to every training frame that shows
	# it (label once's placement); against pseudo-labels in their own frame alone, seed by seed.
	test -f docs/bench/hitl-50-e20-safe-carry-six.json || cp docs/bench/hitl-50-e20-six.json docs/bench/hitl-50-e20-safe-carry-six.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind_safe,full --hold-places --recalibrate-background 0.5 \
	  --pseudo-label-confident 0.6 --carry-pseudo-labels --out docs/bench/hitl-50-e20-safe-carry-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-safe-carry-six --resume --refit-row-share 1 --resume-other-library \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-e20-safe-carry-six.json \
	  docs/bench/hitl-50-e20-safe-pseudo-six.json --readme docs/review-loop.md \
	  --readme-block hitl-50-e20-safe-carry-vs-pseudo-six
	# blind_safe with pseudo-labels alone: the negatives scoring 0.6 or more, off the labels, teach their
	# predicted class, nothing is held below them and the background is not recalibrated (blind and full
	# read back from hitl-50-e20-six), seeds 0-5; then against pseudo-labels with holding, seed by seed.
	test -f docs/bench/hitl-50-e20-pseudo-alone-six.json || cp docs/bench/hitl-50-e20-six.json docs/bench/hitl-50-e20-pseudo-alone-six.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind_safe,full --hold-confident 0.6 \
	  --pseudo-label-confident 0.6 --out docs/bench/hitl-50-e20-pseudo-alone-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-pseudo-alone-six --resume --refit-row-share 1 --resume-other-library \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-e20-pseudo-alone-six.json \
	  docs/bench/hitl-50-e20-safe-pseudo-six.json --readme docs/review-loop.md \
	  --readme-block hitl-50-e20-pseudo-alone-vs-pseudo-six
	# Per-class thresholds tuned out of fold (the training frames in two stretches of the drive, each scored
	# by a model fitted on the other), with no ceiling: blind mining and full labels at 30%, seeds 0, 1, 3, 4,
	# each model measured at these thresholds and at its fitted frames' (the same network). These records
	# fitted each round's fold models afresh (--no-continue-folds), as the code did before it could go on.
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,3,4 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind,full --threshold-folds 2 --no-continue-folds --out docs/bench/hitl-e20-folds-six.json \
	  --readme docs/review-loop.md --readme-block hitl-e20-folds-six --resume --refit-row-share 1 \
	  --threshold-objective class
	# The same, six seeds, thresholds tuned for the F-score of all classes pooled (--threshold-objective total),
	# each model also at the class objective's out-of-fold thresholds; against the record above, seed by seed.
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind,full --threshold-folds 2 --no-continue-folds --threshold-objective total \
	  --out docs/bench/hitl-e20-folds-pooled-six.json --readme docs/review-loop.md \
	  --readme-block hitl-e20-folds-pooled-six --resume --refit-row-share 1
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-e20-folds-pooled-six.json docs/bench/hitl-e20-folds-six.json \
	  --readme docs/review-loop.md --readme-block hitl-e20-folds-pooled-vs-class
	# The same with the reviewer's 200 places a round (blind mining and full labels read back from the record above).
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind,reviewed_200,full --threshold-folds 2 --no-continue-folds --threshold-objective total \
	  --out docs/bench/hitl-e20-folds-pooled-reviewed-six.json --readme docs/review-loop.md \
	  --readme-block hitl-e20-folds-pooled-reviewed-six --resume --refit-row-share 1
	# The same with a person's labels on a handful of points left out of training (fewer than half the policy's).
	test -f docs/bench/hitl-e20-folds-pooled-reviewed-sparse-six.json || cp docs/bench/hitl-e20-folds-pooled-reviewed-six.json docs/bench/hitl-e20-folds-pooled-reviewed-sparse-six.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --label-min-points -1 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind,reviewed_200,full --threshold-folds 2 --no-continue-folds --threshold-objective total \
	  --out docs/bench/hitl-e20-folds-pooled-reviewed-sparse-six.json --readme docs/review-loop.md \
	  --readme-block hitl-e20-folds-pooled-reviewed-sparse-six --resume --refit-row-share 1 --resume-other-library
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-e20-folds-pooled-reviewed-sparse-six.json \
	  docs/bench/hitl-e20-folds-pooled-reviewed-six.json --variants reviewed_200,reviewed_200 \
	  --readme docs/review-loop.md --readme-block hitl-sparse-vs-every-label
	# The same with a person's sparse labels trained on but left out of the thresholds' tuning alone.
	test -f docs/bench/hitl-e20-folds-pooled-reviewed-tune-sparse-six.json || cp docs/bench/hitl-e20-folds-pooled-reviewed-six.json docs/bench/hitl-e20-folds-pooled-reviewed-tune-sparse-six.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points -1 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind,reviewed_200,full --threshold-folds 2 --no-continue-folds --threshold-objective total \
	  --out docs/bench/hitl-e20-folds-pooled-reviewed-tune-sparse-six.json --readme docs/review-loop.md \
	  --readme-block hitl-e20-folds-pooled-reviewed-tune-sparse-six --resume --refit-row-share 1 --resume-other-library
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-e20-folds-pooled-reviewed-tune-sparse-six.json \
	  docs/bench/hitl-e20-folds-pooled-reviewed-six.json --variants reviewed_200,reviewed_200 \
	  --readme docs/review-loop.md --readme-block hitl-tune-sparse-vs-every-label
	# The reviewer's record above on six factories no record had used (simulator seeds 111-116), each
	# network also measured at the thresholds it gets without folds.
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 111,112,113,114,115,116 \
	  --heldout-frames 12 --variants blind,reviewed_200,full --threshold-folds 2 --threshold-objective total \
	  --out docs/bench/hitl-e20-folds-pooled-fresh-six.json --readme docs/review-loop.md \
	  --readme-block hitl-e20-folds-pooled-fresh-six --resume --refit-row-share 1 --resume-other-library
	# The same reviewer on factories 111-116 with a person's sparse labels left out of the thresholds'
	# tuning alone (blind mining and full labels read back from the record above).
	test -f docs/bench/hitl-e20-folds-pooled-fresh-tune-sparse-six.json || cp docs/bench/hitl-e20-folds-pooled-fresh-six.json docs/bench/hitl-e20-folds-pooled-fresh-tune-sparse-six.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points -1 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 111,112,113,114,115,116 \
	  --heldout-frames 12 --variants blind,reviewed_200,full --threshold-folds 2 --threshold-objective total \
	  --out docs/bench/hitl-e20-folds-pooled-fresh-tune-sparse-six.json --readme docs/review-loop.md \
	  --readme-block hitl-e20-folds-pooled-fresh-tune-sparse-six --resume --refit-row-share 1 --resume-other-library
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-e20-folds-pooled-fresh-tune-sparse-six.json \
	  docs/bench/hitl-e20-folds-pooled-fresh-six.json --variants reviewed_200,reviewed_200 \
	  --readme docs/review-loop.md --readme-block hitl-fresh-tune-sparse-vs-every-label \
	  --out docs/bench/hitl-fresh-tune-sparse-vs-every-label.json
	# The floor's pre-registered test: the same three detectors on a third set of six factories
	# (simulator seeds 121-126), then the twelve factories of 111-116 and 121-126 pooled.
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points -1 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 121,122,123,124,125,126 \
	  --heldout-frames 12 --variants blind,reviewed_200,full --threshold-folds 2 --threshold-objective total \
	  --out docs/bench/hitl-e20-folds-pooled-third-tune-sparse-six.json --readme docs/review-loop.md \
	  --readme-block hitl-e20-folds-pooled-third-tune-sparse-six --resume --refit-row-share 1 --resume-other-library
	$(BIN)/factorydet bench hitl-pool docs/bench/hitl-e20-folds-pooled-fresh-tune-sparse-six.json \
	  docs/bench/hitl-e20-folds-pooled-third-tune-sparse-six.json \
	  --readme docs/review-loop.md --readme-block hitl-pool-tune-sparse-twelve \
	  --out docs/bench/hitl-pool-tune-sparse-twelve.json
	# blind_safe (holding places, recalibrating the background) with thresholds out of fold for the pooled F
	# (blind mining and full labels read back from hitl-e20-folds-pooled-six).
	test -f docs/bench/hitl-e20-folds-pooled-safe-six.json || cp docs/bench/hitl-e20-folds-pooled-six.json docs/bench/hitl-e20-folds-pooled-safe-six.json
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind,blind_safe,full --hold-places --recalibrate-background 0.5 \
	  --threshold-folds 2 --no-continue-folds --threshold-objective total --out docs/bench/hitl-e20-folds-pooled-safe-six.json \
	  --readme docs/review-loop.md --readme-block hitl-e20-folds-pooled-safe-six --resume --refit-row-share 1 --resume-other-library
	# The same at 50% unannotated, all three detectors trained with out-of-fold pooled thresholds, seeds 0-5.
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind,full,blind_safe --hold-places --recalibrate-background 0.5 \
	  --threshold-folds 2 --no-continue-folds --threshold-objective total \
	  --out docs/bench/hitl-50-e20-folds-pooled-safe-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-folds-pooled-safe-six --resume --refit-row-share 1 --resume-other-library
	# The same with the reviewer's 200 places a round (blind mining and full labels read back from the record above).
	test -f docs/bench/hitl-50-e20-folds-pooled-reviewed-six.json || cp docs/bench/hitl-50-e20-folds-pooled-safe-six.json docs/bench/hitl-50-e20-folds-pooled-reviewed-six.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind,reviewed_200,full \
	  --threshold-folds 2 --no-continue-folds --threshold-objective total \
	  --out docs/bench/hitl-50-e20-folds-pooled-reviewed-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-folds-pooled-reviewed-six --resume --refit-row-share 1 --resume-other-library
	# The same with a person's labels on a handful of points left out of training (fewer than half the policy's).
	test -f docs/bench/hitl-50-e20-folds-pooled-reviewed-sparse-six.json || cp docs/bench/hitl-50-e20-folds-pooled-reviewed-six.json docs/bench/hitl-50-e20-folds-pooled-reviewed-sparse-six.json
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --label-min-points -1 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4,5 --review-by place --queue-order class \
	  --review-order learned --review-extra -1 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants blind,reviewed_200,full \
	  --threshold-folds 2 --no-continue-folds --threshold-objective total \
	  --out docs/bench/hitl-50-e20-folds-pooled-reviewed-sparse-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-folds-pooled-reviewed-sparse-six --resume --refit-row-share 1 --resume-other-library
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-e20-folds-pooled-reviewed-sparse-six.json \
	  docs/bench/hitl-50-e20-folds-pooled-reviewed-six.json --variants reviewed_200,reviewed_200 \
	  --readme docs/review-loop.md --readme-block hitl-50-sparse-vs-every-label
	# The app's training defaults at 50% with the 20-epoch first fit: the paper's score cut, the learned review
	# order over the mined queue alone (--review-extra 0); against the class-turns record above.
	$(BIN)/factorydet bench hitl $(CORPUS50) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 20 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3 --review-by place --queue-order score \
	  --review-order learned --review-extra 0 --heldout --heldout-seeds 101,102,103,104,105,106 \
	  --heldout-frames 12 --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-50-e20-score-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-score-six --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-50-e20-score-six.json docs/bench/hitl-50-e20-six.json \
	  --readme docs/review-loop.md --readme-block hitl-50-e20-score-vs-class-six
	# Every round trained afresh (the paper's procedure; --round-epochs 0), blind, the learned
	# order's reviewer and full labels alike (30%), against the learned record's rounds that go on.
	$(BIN)/factorydet bench hitl $(CORPUS) --threshold-label-min-points 0 --train-frames 8 --frames 10 --budgets 200 --rounds 2 --epochs 5 \
	  --mining-threshold 0.05 --hide-labelled 0.25 --seeds 0,1,2,3,4 --review-by place --queue-order class \
	  --review-order learned --round-epochs 0 --heldout --heldout-seeds 101,102,103 --heldout-frames 12 \
	  --variants reviewed_200,full --model-box-targets --out docs/bench/hitl-review-afresh-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-review-afresh-heldout --resume --refit-row-share 1 \
	  --threshold-folds 0 --threshold-objective class
	$(BIN)/factorydet bench hitl-compare docs/bench/hitl-review-afresh-heldout.json \
	  docs/bench/hitl-review-learned-heldout.json --readme docs/review-loop.md \
	  --readme-block hitl-review-afresh-vs-learned-heldout
	# The paper's data set size (6,389 frames of 80k points, 2/3 training) simulated and detected on
	# Ray workers (about three hours on 2 cores), inside a loopback-only network namespace; the
	# record is kept after each run and a re-run does only the runs it lacks.
	$(BIN)/python -m factorydet_core.scale.netns -- $(BIN)/factorydet bench scale $(SCALE_DATA) \
	  --simulate-frames 6389 --seed 301 --frame-counts 100,6389 --evaluate-frames 2130 \
	  --out $(SCALE_DATA).bench.json --resume --readme docs/scaling.md

# Screenshots of the README's labelling walkthrough, taken by driving the app in headless Chromium.
screenshots: $(STAMP) demo browserdeps
	$(BIN)/python -m app.screenshots sessions/demo/data --out docs/img

# The shipped model's training data: a simulated factory of another seed than the demo's.
CORPUS ?= /tmp/factorydet_corpus
corpus: $(STAMP)
	@[ -f $(CORPUS)/manifest.json ] || $(BIN)/factorydet simulate --out $(CORPUS) --frames 60 --seed 1

# The same factory with half its objects unannotated (bench hitl's second block).
CORPUS50 ?= /tmp/factorydet_corpus50
corpus50: $(STAMP)
	@[ -f $(CORPUS50)/manifest.json ] || $(BIN)/factorydet simulate --out $(CORPUS50) --frames 60 --seed 1 \
	  --unlabelled-fraction 0.5

# Retrains the shipped checkpoint: the learned box head classifying, the box quality regressor boxing
# (about forty minutes on 2 cores; see docs/pipeline.md, "The default model"). paper-model writes the
# paper's pipeline as paper.pt, the benchmarks' reference.
default-model: $(STAMP) corpus
	$(BIN)/factorydet train $(CORPUS) --session corpus-head --method head_options --rounds 1 --epochs 20 \
	  --round-epochs 0 --class-weight sqrt --threshold-folds 0 --threshold-objective class --set feature=direct \
	  --export factorydet_core/models/default.pt

paper-model: $(STAMP) corpus
	$(BIN)/factorydet train $(CORPUS) --session corpus-paper --method paper --rounds 1 --epochs 10 \
	  --round-epochs 0 --class-weight balanced --fragments-per-frame 300 --score-threshold 0.35 --probability-exponent 0.5 \
	  --set feature=direct --export factorydet_core/models/paper.pt

# Regenerates docs/results.md (tables, PR curve, grid sweep) for the shipped model on the demo data;
# the baseline and the sweep train on the shipped model's training corpus.
report: $(STAMP) demo corpus
	$(BIN)/factorydet report sessions/demo/data --model default --train-data $(CORPUS) --out docs/results.md \
	  --sweep 0.15,0.2,0.3 --sweep-frames 2

# open3d links against libusb-1.0 at import time.
sysdeps:
	@if ! ldconfig -p | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$(IS_ROOT)" = yes ]; then $(APT_GET) update -qq && $(APT_GET) install -y -qq libusb-1.0-0; \
	  else echo "open3d needs libusb-1.0-0; run: sudo apt-get install -y libusb-1.0-0" >&2; exit 1; fi; \
	fi
	@if ! ldconfig -p | grep -q 'libgomp.so.1'; then \
	  if [ "$(IS_ROOT)" = yes ]; then $(APT_GET) update -qq && $(APT_GET) install -y -qq libgomp1; \
	  else echo "numba's threads need libgomp1; run: sudo apt-get install -y libgomp1" >&2; exit 1; fi; \
	fi
	@if ! $(PYTHON) -c 'import ensurepip, venv' >/dev/null 2>&1; then \
	  if [ "$(IS_ROOT)" = yes ]; then $(APT_GET) update -qq && $(APT_GET) install -y -qq python3-venv; \
	  else echo "Python's venv module is missing; run: sudo apt-get install -y python3-venv" >&2; exit 1; fi; \
	fi

# The browser test drives Debian's chromium through Playwright (no browser download); its WebGL
# runs on Mesa's llvmpipe through EGL (app/screenshots.py's ARGS; without Mesa's EGL Chromium
# falls back to its slower SwiftShader).
browserdeps:
	@if [ ! -x /usr/bin/chromium ]; then \
	  if [ "$(IS_ROOT)" = yes ]; then $(APT_GET) update -qq && $(APT_GET) install -y -qq chromium; \
	  else echo "The browser test needs Debian's chromium; run: sudo apt-get install -y chromium" >&2; exit 1; fi; \
	fi
	@if ! ldconfig -p | grep -q 'libEGL.so.1 ' || ! ldconfig -p | grep -q 'libEGL_mesa.so.0' \
	    || ! ls /usr/lib/*/dri/swrast_dri.so >/dev/null 2>&1; then \
	  if [ "$(IS_ROOT)" = yes ]; then $(APT_GET) update -qq && $(APT_GET) install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri; \
	  else echo "The browser test's WebGL needs Mesa's EGL; run: sudo apt-get install -y libegl1 libegl-mesa0 libgl1-mesa-dri" >&2; exit 1; fi; \
	fi

# torch is pinned and installed first: this exact version is a CPU build on this machine's disk,
# whereas a version range would make pip pull a multi-GB CUDA build.
$(STAMP): pyproject.toml | sysdeps
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "factorydet needs Python >= 3.11"'
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e '.[dev,scale]'
	$(BIN)/python -m factorydet_core.detection.warmup  # compiles the numba kernels once (about half a minute)
	touch $(STAMP)

clean:
	rm -rf $(VENV) build *.egg-info
