# greyfit service image. Build: docker build -t greyfit .   Run: docker run -p 8000:8000 -v greyfit-data:/data greyfit
FROM python:3.11-slim

# gcc compiles each model's per-sample functions once (cached under /data/cache); without it greyfit
# falls back to CasADi's interpreter, 2-3x slower on long records. (The Tiny C Compiler, which
# compiles them in milliseconds for a new model's first fits while gcc builds, comes with the
# `quick` extra below.)
# tini runs as PID 1: it reaps the processes a killed fit worker leaves behind (its compilers), which a
# server as PID 1 would leave as zombies, and the container ends with the server (its workers with it).
RUN apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev tini \
 && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home --uid 10001 greyfit && mkdir /data && chown greyfit /data
WORKDIR /app
RUN chown greyfit /app
USER greyfit

# Dependencies first (a layer that survives source changes): the project's own install step on
# empty package stubs, the same scripts/install.sh the README and CI use.
COPY --chown=greyfit pyproject.toml README.md constraints.txt ./
COPY --chown=greyfit scripts/install.sh scripts/stub_packages.py scripts/
RUN python3 scripts/stub_packages.py \
 && bash scripts/install.sh report,quick,files \
 && .venv/bin/python -c "import matplotlib.font_manager"
# (the last step builds matplotlib's font cache in the image: otherwise each new container's first
# report pays for it, about a second)

# The source; the editable install above already points at /app.
COPY --chown=greyfit schemas schemas
COPY --chown=greyfit solvers solvers
COPY --chown=greyfit service service
COPY --chown=greyfit greyfit greyfit
COPY --chown=greyfit examples examples
# their bytecode in the image: each new container's first fit would compile ~100 modules (0.1 s)
RUN .venv/bin/python -m compileall -q greyfit schemas solvers service > /dev/null

ENV GREYFIT_DATA_DIR=/data PYTHONUNBUFFERED=1
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=20s --retries=3 \
  CMD .venv/bin/python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz', timeout=4)"
ENTRYPOINT ["/usr/bin/tini", "--"]
CMD [".venv/bin/greyfit", "serve", "--host", "0.0.0.0", "--port", "8000"]
