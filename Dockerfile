# One image for every fleetslam process: `docker run fleetslam router|robot|central|...`
# (docker-compose.yml runs the whole fleet from it).
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
    && mkdir -p /reports /state /data \
    && chown -R fleetslam /reports /state /opt/numba-cache

USER fleetslam
WORKDIR /home/fleetslam
EXPOSE 7447
ENTRYPOINT ["fleetslam"]
CMD ["--help"]
