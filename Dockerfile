# One image for the map server and the agents (the zenoh router is the official eclipse/zenoh image).
FROM python:3.11-slim
ENV PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /app
COPY pyproject.toml README.md ./
COPY shared ./shared
COPY robot_agent ./robot_agent
COPY map_server ./map_server
COPY fleet_slam ./fleet_slam
RUN pip install . && useradd --create-home --uid 1000 fleet && mkdir -p /state /out && chown fleet /state /out
USER fleet
# Python as PID 1 ignores SIGTERM unless it handles it: the services do (shared.bus.stop_on_signals),
# and compose runs them with `init: true` as well.
CMD ["python", "-m", "map_server", "--help"]
