# The farm dashboard: a slim Python image and this project with the dashboard extra.
# Build from the repository root:
#   docker build -f k8s/images/dashboard.Dockerfile -t shaderball-dashboard .
FROM python:3.11-slim

RUN useradd --create-home --uid 10001 shaderball
WORKDIR /opt/shaderball
COPY pyproject.toml README.md ./
COPY farm farm
COPY render_jobs render_jobs
COPY storage storage
COPY trainer trainer
# this repository itself; its dependencies are pinned in pyproject.toml
# hadolint ignore=DL3013
RUN pip install --no-cache-dir ".[dashboard]"
USER 10001
EXPOSE 8266
ENTRYPOINT ["farm"]
CMD ["dashboard", "--host", "0.0.0.0"]
