# facewire in a container: Debian 12, Python 3.11, Mesa's EGL for offscreen rendering.
FROM python:3.11-slim-bookworm
RUN apt-get update \
    && apt-get install -y --no-install-recommends libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libgles2 libportaudio2 \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY facewire facewire
COPY models models
COPY sender sender
COPY receiver receiver
COPY protocol protocol
RUN pip install --no-cache-dir .
ENV PYOPENGL_PLATFORM=egl
# A call: updates and snapshots on 5555 and 5556 (5557, 5558 for `facewire call`); the
# receiver's live view on 8080.
EXPOSE 5555-5558 8080
WORKDIR /out
ENTRYPOINT ["facewire"]
