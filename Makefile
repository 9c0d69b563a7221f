# Every target sets itself up: a fresh clone needs only Python 3.11 and make.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin

.PHONY: demo demo-train test lint chromium quality bench-frames bench-dashboard bench-render bench-farm bench-farm-scale bench-store bench-train bench-infer bench-viewer bench-materials bench-storage bench-learning bench-flops bench-report gpu-wheels gpu-stores gpu-carry gpu-learn-back learn-store-500 learn-store-700 learn-store-800 learn-test-store bench-render-bits clean

# torch: the CPU build these machines keep in pip's find-links folder, when it is there. A plain
# torch==2.13.0 resolves to PyPI's CUDA build (2.13.0+cu130 sorts above 2.13.0+cpu): gigabytes of
# nvidia-* downloads that a CPU machine never uses and a flaky network can fail.
TORCH ?= $(if $(wildcard /opt/wheels/torch-2.13.0+cpu-*.whl),torch==2.13.0+cpu,torch==2.13.0)
FIND_LINKS := $(if $(wildcard /opt/wheels),--find-links /opt/wheels)

# uv installs: downloads in parallel, unpacks and compiles the bytecode on every core (65 s for
# a fresh environment here against pip's 207 s: docs/development.md). uv reads no pip
# configuration, hence the find-links folder named here; where it fails (an index only pip's
# configuration names, say), pip installs the same. The retries: bpy and Ray come from PyPI,
# and a download has been seen to fail mid-wheel on these machines.
$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --retries 10 'uv==0.13.*'
	UV_HTTP_RETRIES=10 UV_HTTP_TIMEOUT=180 $(BIN)/uv pip install --quiet \
		--python $(BIN)/python --compile-bytecode $(FIND_LINKS) -e '.[all,dev]' '$(TORCH)' || \
		{ echo "uv could not install the environment: pip installs it"; \
		$(BIN)/pip install --quiet --retries 10 --upgrade pip && \
		$(BIN)/pip install --quiet --retries 10 --resume-retries 20 -e '.[all,dev]' '$(TORCH)'; }
	touch $@

# The main job on the embedded default (local Ray, local store): a small real farm job,
# 4 uniform + 4 procedural materials x 5 suns at 128² / 32 spp, then what the store holds.
demo: $(BIN)/.installed
	$(BIN)/farm submit --materials uniform:4 --materials procedural:4 --resolution 128 \
		--samples 32 --shard-size 10 --out out/demo.zarr
	$(BIN)/shards info out/demo.zarr

# Then a short training run on that store (40 epochs of the default recipe, 360 steps: about 2
# minutes on 2 CPU cores, or all GPUs), long enough for the ball's shape to show, and its
# metrics and picture grid (out/runs/demo/eval.png).
demo-train: $(BIN)/.installed
	test -f out/demo.zarr/zarr.json || $(MAKE) demo
	rm -rf out/runs/demo
	$(BIN)/trainer launch --store out/demo.zarr --epochs 40 --out out/runs/demo
	$(BIN)/trainer eval --checkpoint out/runs/demo

# Two pytest workers: the suite is CPU-bound on 2 cores, and a third worker made it slower
# (docs/development.md). A test kills only processes it started, so any two run side by side.
# The 25 slowest tests are listed at the end: where the suite's time goes.
test: $(BIN)/.installed lint chromium
	$(BIN)/pytest -q -n 2 --dist worksteal --durations=25

# The page tests drive Debian's Chromium (headless, through Playwright); CI runs as root.
# When it cannot be installed, those tests fail saying so; the rest still run.
chromium:
	@test -x /usr/bin/chromium || (apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
		apt-get install -y -qq chromium >/dev/null) || \
		echo "could not install Debian's chromium package: the browser tests will fail"

lint: $(BIN)/.installed
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# The paper's Table 1 here: renders, trainings, scores, docs/quality.md (hours; resumes).
quality: $(BIN)/.installed chromium
	$(BIN)/python -m benchmarks.quality

# The quality table's frame times, re-timed side by side in one run (about a minute).
bench-frames: $(BIN)/.installed
	$(BIN)/python -m benchmarks.frame_times

bench-render: $(BIN)/.installed
	$(BIN)/python -m benchmarks.render

bench-farm: $(BIN)/.installed
	$(BIN)/python -m benchmarks.farm

# One driver's ceilings: its scheduling policy (1,000 workers) and its 400² shard commits.
bench-dashboard: $(BIN)/.installed chromium
	$(BIN)/python -m benchmarks.dashboard

bench-farm-scale: $(BIN)/.installed
	$(BIN)/python -m benchmarks.farm_scale

# Training and inference at 400² (renders out/bench-400.zarr with the farm on first use).
# bench-store renders only that store (about a minute), e.g. to carry to a GPU machine.
bench-store: $(BIN)/.installed
	$(BIN)/python -c "from benchmarks.trainstore import ensure_store; print(ensure_store())"

bench-train: $(BIN)/.installed
	$(BIN)/python -m benchmarks.train

bench-infer: $(BIN)/.installed
	$(BIN)/python -m benchmarks.infer

# The viewer: an edit's mapping, network and encoding times at 128², 256², 400².
bench-viewer: $(BIN)/.installed
	$(BIN)/python -m benchmarks.viewer

# The material reader: time and peak memory of reading one 4K library material, three layouts.
bench-materials: $(BIN)/.installed
	$(BIN)/python -m benchmarks.materials

# For a GPU machine with CUDA torch but no package registry (benchmarks/gpu.sh says how):
# the packages the store and the trainer need that its image lacks, as wheels for its Python
# (GPU_PYTHON, the device's is 3.12) in .whl/ (torch, tensorboard, pillow,
# click, fsspec and tqdm are in the device's image).
GPU_PYTHON ?= 3.12
gpu-wheels: $(BIN)/.installed
	$(BIN)/pip download --quiet --only-binary=:all: --no-deps --python-version $(GPU_PYTHON) \
		--platform manylinux2014_x86_64 --platform manylinux_2_28_x86_64 \
		--platform manylinux1_x86_64 -d .whl 'zarr>=3.1,<3.2' 'numcodecs>=0.14' donfig crc32c \
		'google-crc32c>=1.5' tenacity flip-evaluator

# The stores the GPU benchmarks read, made here by the farm (once): out/bench-400.zarr (train,
# infer) and out/gpu-learn-64-1100.zarr (learn: 1,100 materials x 5 suns at 64², 32 spp, its
# renders kept at 4 mantissa bits: 50.2 MB, so that it, .whl/ and the checkout fit one device
# call's 64 MiB; make gpu-carry checks). out/gpu-learn-64.zarr (500 materials, every bit) is
# the store the CPU's batch-128 learning tables read (learning-64-b128-*),
# out/gpu-learn-64-700.zarr (700, 6 bits) learning-64-700-b128-default-384k's and
# out/gpu-learn-64-800.zarr (800, 6 bits) the learning-64-800-b128-* tables'.
LEARN_STORE := out/gpu-learn-64-1100.zarr
# $(call learn-store,STORE,MATERIALS OF EACH KIND,MORE FARM FLAGS): a 64², 32-spp store of
# half uniform, half procedural materials, rendered unless it is there
learn-store = test -f $(1)/zarr.json || $(BIN)/farm submit -m uniform:$(2) -m procedural:$(2) \
	--resolution 64 --samples 32 --shard-size 25 --no-ray-dashboard $(3) -o $(1)

gpu-stores: bench-store
	$(call learn-store,$(LEARN_STORE),550,--render-bits 4)

learn-store-500: $(BIN)/.installed
	$(call learn-store,out/gpu-learn-64.zarr,250)

learn-store-700: $(BIN)/.installed
	$(call learn-store,out/gpu-learn-64-700.zarr,350,--render-bits 6)

learn-store-800: $(BIN)/.installed
	$(call learn-store,out/gpu-learn-64-800.zarr,400,--render-bits 6)

# 120 materials none of the stores above holds (another --seed): runs on different stores
# are compared on it (trainer eval --checkpoint A --checkpoint B --on out/learn-test-64.zarr)
learn-test-store: $(BIN)/.installed
	$(call learn-store,out/learn-test-64.zarr,60,--seed 1)

# After a `gpu.sh learn` device call, FROM the folder its files came back to: the table and
# grid where make bench-report reads them, the networks joined in out/gpu-learn and scored
# here, paired, on the run's held-out materials and on out/learn-test-64.zarr's (ARGS: more
# options, e.g. ARGS="--also out/learn1100/64/384000/default": the CPU's 384k-pass run on the
# same store, table learning-64-1100-b128-default-384k, where this machine still has it)
gpu-learn-back: $(BIN)/.installed
	@test -n "$(FROM)" || { echo "make gpu-learn-back FROM=FOLDER: the device call's files" >&2; exit 2; }
	$(BIN)/python -m benchmarks.gpu_learn_back $(FROM) $(ARGS)

# What `gpu.sh learn`'s device call carries: the checkout's files (tracked, and untracked
# ones git does not ignore), the store and .whl/, in file bytes; refused over 64 MiB
GPU_CARRY_LIMIT := 67108864
gpu-carry:
	@total=$$( { git ls-files -z --cached --others --exclude-standard | \
		xargs -0 stat -c %s 2>/dev/null; find $(LEARN_STORE) .whl -type f -printf '%s\n'; } | \
		awk '{s += $$1} END {print s}'); \
	echo "a device call carries $$total bytes of files ($$((total * 100 / $(GPU_CARRY_LIMIT))) % of 64 MiB)"; \
	test "$$total" -le $(GPU_CARRY_LIMIT) || { echo "over the 64 MiB a call carries" >&2; exit 1; }

# How much each recipe learns per image pass (hours on 2 cores; resumes row by row)
# every row at 16k image passes; at 64k the paper's network, the default, the shaderball row and
# its one-change rows: the cue and batch the default takes from it, the widths that learnt the
# most per pass at 16k, a head and a deeper decoder, batch 32 at three rates, and the default
# in fp32, at widths 32 and 48, and at width 32 with weight decay and with a higher rate (each
# 64k row is 10-85 min on 2 cores)
LEARNING_64K := onecycle,default,default-fp32,default-w32,default-wd,default-lr3e-3,default-w48,shaderball,sb-batch4,sb-batch4-lr1e-3,sb-ambient,sb-ambient-b4,sb-ambient-b2,sb-w48,sb-w48-b4,sb-w64-b4,sb-w64-b2,sb-w64-b4-seed1,sb-w80-b4,sb-w80-b4-seed1,sb-head,sb-dec2,sb-batch32,sb-batch32-lr4e-3,sb-batch32-lr8e-3
bench-learning: $(BIN)/.installed
	$(BIN)/python -m benchmarks.learning --budget 16000
	$(BIN)/python -m benchmarks.learning --budget 64000 --rows $(LEARNING_64K) --grid-rows onecycle,default,sb-w80-b4
	$(BIN)/python -m benchmarks.truth_noise --budget 64000 --rows $(LEARNING_64K)
	$(BIN)/python -m benchmarks.learning --resolution 128 --budget 8000 --rows onecycle,shaderball,default-w32,default --grid-rows onecycle,default-w32,default

# docs/benchmarks.md from every table in benchmarks/results/
bench-report: $(BIN)/.installed
	$(BIN)/python -m benchmarks.report

# MDS (mosaicml-streaming) needs torchvision, so the storage benchmark has its own environment:
# torch 2.14.1 + torchvision 0.29.1 (about 6 GB), kept apart from the project's.
.venv-bench/bin/.installed: pyproject.toml
	$(PYTHON) -m venv .venv-bench
	.venv-bench/bin/pip install --quiet --upgrade pip
	.venv-bench/bin/pip install --quiet -e '.[all,dev]' torch==2.14.1 torchvision==0.29.1 \
		mosaicml-streaming webdataset
	touch $@

bench-storage: .venv-bench/bin/.installed
	.venv-bench/bin/python -m benchmarks.storage

# the FLOPs of a training image pass of the rows gpu.sh learn trains, at 64² and 128²
bench-flops: $(BIN)/.installed
	$(BIN)/python -m benchmarks.pass_flops --resolution 64 --resolution 128

# what each count of --render-bits saves and costs, on the 500-material store (every bit)
bench-render-bits: learn-store-500
	$(BIN)/python -m benchmarks.render_bits --store out/gpu-learn-64.zarr

clean:
	rm -rf $(VENV) .venv-bench out .pytest_cache .ruff_cache
