# The BAM Study server. It runs from the source tree (alembic.ini and migrations/ are found
# there) and takes its settings from BAM_* variables; BAM_DATABASE_URL is a PostgreSQL URL, e.g.
#   postgresql+psycopg://bam:PASSWORD@db:5432/bam
# compose.yaml runs it with PostgreSQL beside it and applies the migrations first
# (`bam-study db upgrade`); on its own, `serve` refuses an out-of-date schema.
# PYTHON_IMAGE: another image with Python 3.11 and pip, e.g. from a registry mirror.
ARG PYTHON_IMAGE=python:3.11-slim
FROM ${PYTHON_IMAGE}

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    BAM_UPDATE_WORKERS=2

WORKDIR /app

# GNU OpenMP, for the planner's passes on numba's OpenMP threads (without it they fall back to a
# Python thread pool, slower to hand work over); the slim image does not have it.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgomp1 \
    && rm -rf /var/lib/apt/lists/*

# The dependencies first, in their own layer: it is rebuilt only when pyproject.toml changes.
# With the "dask" extra: the server can send its learner updates to a Dask cluster
# (BAM_UPDATE_SCHEDULER), and the image can run the cluster's scheduler and workers
# (`dask scheduler`, `dask worker tcp://SCHEDULER:8786`; see docs/cluster.md).
COPY pyproject.toml ./
RUN python -c "import subprocess, sys, tomllib; \
project = tomllib.load(open('pyproject.toml', 'rb'))['project']; \
deps = project['dependencies'] + project['optional-dependencies']['dask']; \
subprocess.check_call([sys.executable, '-m', 'pip', 'install', *deps])"

COPY . .
RUN pip install --no-deps -e . \
    && useradd --create-home --uid 10001 bam

USER bam
# The learners' compiled kernels, in numba's cache in the image (the bam user's ~/.cache): the
# update processes load them when they start (about 0.4 s) instead of compiling them (about a
# minute of a core). The cache is made for this machine's CPU; on another, they compile at
# start. Compiled by two processes side by side, each kernel once.
RUN python -c "from server.app.updates.compiling import warm_up_in_processes; warm_up_in_processes(2)"
EXPOSE 8000

# Healthy once every update process has loaded the learners' compiled kernels (503 before).
# (A container running `dask scheduler` or `dask worker` serves no page: run it with
# --no-healthcheck, as compose.yaml's cluster profile does.)
HEALTHCHECK --interval=10s --timeout=5s --start-period=120s --retries=3 \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/api/health', timeout=4)"

# Behind a TLS proxy (needed for MTurk's https iframe), set BAM_FORWARDED_ALLOW_IPS to the
# proxy's address so that the server believes its X-Forwarded-* headers (none by default).
CMD ["bam-study", "serve", "--host", "0.0.0.0", "--port", "8000"]
