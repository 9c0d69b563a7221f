# Render worker and farm driver: Ray's image at the pinned Ray and Python 3.11 (bpy 4.5 needs
# exactly 3.11), the system libraries bpy loads, and this project with the render and farm
# extras. Used by the RayCluster's head and workers and by the RayJob's submitter.
# Build from the repository root:
#   docker build -f k8s/images/render-worker.Dockerfile -t shaderball-render .
FROM rayproject/ray:2.60.0-py311

USER 0
# bpy 4.5 links X11, GL and xkbcommon libraries even when it renders headless
RUN apt-get update \
    && apt-get install -y --no-install-recommends \
        libxrender1=1:0.9.* libxxf86vm1=1:1.1.* libxfixes3=1:6.0.* libxi6=2:1.8.* \
        libxkbcommon0=1.4.* libgl1=1.4.* libsm6=2:1.2.* libice6=2:1.0.* \
    && rm -rf /var/lib/apt/lists/*
USER 1000
WORKDIR /home/ray/shaderball
COPY --chown=1000:100 pyproject.toml README.md ./
COPY --chown=1000:100 farm farm
COPY --chown=1000:100 render_jobs render_jobs
COPY --chown=1000:100 storage storage
COPY --chown=1000:100 trainer trainer
# this repository itself; its dependencies are pinned in pyproject.toml
# hadolint ignore=DL3013
RUN pip install --no-cache-dir ".[render,farm]" \
    && python -c "import bpy; print(bpy.app.version_string)"
