# Trainer: a CUDA PyTorch image (torch comes with it) and this project with the train extra;
# no Blender. Used by the TrainJob on the torch-distributed runtime.
# Build from the repository root:
#   docker build -f k8s/images/trainer.Dockerfile -t shaderball-trainer .
FROM pytorch/pytorch:2.11.0-cuda12.8-cudnn9-runtime

WORKDIR /opt/shaderball
COPY pyproject.toml README.md ./
COPY farm farm
COPY render_jobs render_jobs
COPY storage storage
COPY trainer trainer
# this repository itself; its dependencies are pinned in pyproject.toml
# hadolint ignore=DL3013
RUN pip install --no-cache-dir ".[train]" \
    && python -c "import torch, trainer.train; print(torch.__version__)"
ENTRYPOINT []
