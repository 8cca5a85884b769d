# One image for the server and the device simulators; the command picks which.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1
WORKDIR /app
RUN apt-get update \
    && apt-get install -y --no-install-recommends libgl1 libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*
COPY pyproject.toml constraints.txt README.md ./
COPY server ./server
COPY clients ./clients
RUN pip install --no-cache-dir -c constraints.txt .

# The cell runs as its own unprivileged user. /data is made here, owned by it, so
# a named volume mounted there starts out owned by it too; the server keeps it 0700.
RUN groupadd --system --gid 10001 glue \
    && useradd --system --uid 10001 --gid glue --home-dir /data --no-create-home \
        --shell /usr/sbin/nologin glue \
    && mkdir /data && chown glue:glue /data && chmod 0700 /data
USER glue:glue
VOLUME ["/data"]

EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=5s --retries=3 --start-period=120s \
    CMD ["python", "-m", "server.cli.healthcheck", "http://127.0.0.1:8000/health"]
CMD ["glue-server", "--host", "0.0.0.0", "--port", "8000", "--data-dir", "/data"]
