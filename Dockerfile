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

EXPOSE 8000
CMD ["glue-server", "--host", "0.0.0.0", "--port", "8000", "--data-dir", "/data"]
