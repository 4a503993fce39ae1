# One image for the API, the workers and the migration job.
# Mesa's EGL renders on the CPU; on a host with the NVIDIA container toolkit, asking for the
# "graphics" driver capability mounts NVIDIA's EGL, which glvnd then prefers (see docker-compose.yml).
FROM python:3.11-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    NVIDIA_DRIVER_CAPABILITIES=graphics,compute,utility \
    VP_MODELS_DIR=/srv/vehicle_models

RUN apt-get update \
 && apt-get install -y --no-install-recommends libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 libglvnd0 libopengl0 \
 && rm -rf /var/lib/apt/lists/* \
 && useradd --create-home --uid 1000 vp

WORKDIR /srv
COPY pyproject.toml README.md alembic.ini ./
COPY vehicle_pose ./vehicle_pose
COPY app ./app
COPY worker ./worker
COPY core ./core
RUN pip install '.[service,postgres,s3]' \
 && python -c "from vehicle_pose.loss.moments import warm_up; warm_up()" \
 && python -c "import numpy as np; from vehicle_pose.model.loading import oriented_faces; oriented_faces(np.array([[0, 1, 2], [0, 1, 3]]))" \
 && mkdir -p /prepared && chown vp /prepared
COPY vehicle_models ./vehicle_models

USER vp
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz')" || exit 1
CMD ["uvicorn", "--factory", "app.main:create_app", "--host", "0.0.0.0", "--port", "8000", "--workers", "2", "--proxy-headers"]
