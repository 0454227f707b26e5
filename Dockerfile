# tidee: one image for every tidee process (router, server, agent, viewer); compose.yaml picks the command.
FROM python:3.11-slim
RUN apt-get update && apt-get install -y --no-install-recommends \
        libegl1 libegl-mesa0 libgl1-mesa-dri make && \
    rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY tidee tidee
COPY protocol protocol
COPY server server
COPY agent agent
COPY viewer viewer
# torch pinned first: an unpinned torch pulls GBs of CUDA wheels.
RUN pip install --no-cache-dir "torch==2.13.0" && pip install --no-cache-dir ".[agent,viewer]"
ENTRYPOINT ["tidee"]
CMD ["server", "--renderer", "auto"]
