# One image for the lab's three services (docker-compose.yml): the rig, the campaign, the fit.
FROM python:3.11-slim
# mbpoll and socat are for the test suite and for poking the rig by hand; not for the services
RUN apt-get update && apt-get install -y --no-install-recommends mbpoll socat \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY rig_sim rig_sim
COPY cbc_controller cbc_controller
COPY ude_fit ude_fit
COPY campaigns campaigns
RUN pip install --no-cache-dir .
# matplotlib and numba want a writable cache; the services run as this user
RUN useradd --create-home lab && mkdir /data && chown lab /data
USER lab
ENV MPLCONFIGDIR=/tmp/matplotlib NUMBA_CACHE_DIR=/tmp/numba
VOLUME /data
EXPOSE 5020
