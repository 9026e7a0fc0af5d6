# One image for the map server and the agents (the zenoh router is the official eclipse/zenoh image).
# The C kernels (robot_agent/slam/_kernels.c, shared/_kernels.c) are compiled in a build stage that has a C
# compiler; the image itself gets the built wheel only.
FROM python:3.11-slim AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY pyproject.toml setup.py README.md ./
COPY shared ./shared
COPY robot_agent ./robot_agent
COPY map_server ./map_server
COPY fleet_slam ./fleet_slam
RUN pip wheel --no-deps --wheel-dir /wheels .

FROM python:3.11-slim
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
COPY --from=build /wheels /wheels
RUN pip install /wheels/*.whl && rm -rf /wheels \
    && python -c "from robot_agent.slam import kernels as a; from shared import kernels as b; assert a.AVAILABLE and b.AVAILABLE, 'C kernels not built'" \
    && useradd --create-home --uid 1000 fleet && mkdir -p /state /out && chown fleet /state /out
WORKDIR /app
USER fleet
# Python as PID 1 ignores SIGTERM unless it handles it: the services do (shared.bus.stop_on_signals),
# and compose runs them with `init: true` as well.
CMD ["python", "-m", "map_server", "--help"]
