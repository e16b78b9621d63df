# One image for every fleetslam process: `docker run fleetslam router|robot|central|...`
# (docker-compose.yml runs the whole fleet from it). /secrets is where the compose router makes the
# fleet's passwords: a new volume mounted there takes this folder's owner (the image's user) and mode 0700.
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    NUMBA_CACHE_DIR=/opt/numba-cache

WORKDIR /app
COPY pyproject.toml README.md ./
COPY schemas ./schemas
COPY robots ./robots
COPY central ./central
COPY services ./services
# The numba kernels are compiled here, from the installed package (not /app), into NUMBA_CACHE_DIR:
# no service waits for the compiler at start.
RUN pip install . \
    && useradd --create-home --uid 10001 --shell /usr/sbin/nologin fleetslam \
    && cd / && python -c "from services import compiled; print(f'kernels compiled in {compiled.warm_up():.1f} s')" \
    && mkdir -p /reports /state /data /secrets \
    && chown -R fleetslam /reports /state /secrets /opt/numba-cache \
    && chmod 700 /secrets

USER fleetslam
WORKDIR /home/fleetslam
EXPOSE 7447
ENTRYPOINT ["fleetslam"]
CMD ["--help"]
