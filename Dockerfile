# One image for every fleetslam process: `docker run fleetslam router|robot|central|...`
# (docker-compose.yml runs the whole fleet from it).
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /app
COPY pyproject.toml README.md ./
COPY schemas ./schemas
COPY robots ./robots
COPY central ./central
COPY services ./services
RUN pip install . \
    && useradd --create-home --uid 10001 --shell /usr/sbin/nologin fleetslam \
    && mkdir -p /reports /data \
    && chown fleetslam /reports

USER fleetslam
WORKDIR /home/fleetslam
EXPOSE 7447
ENTRYPOINT ["fleetslam"]
CMD ["--help"]
