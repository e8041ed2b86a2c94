# device set-up (sourced): carried wheels and the stripped open3d 0.19 CPU build into /tmp/site
if [ ! -f /tmp/site/.done ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || return 1
  tar xJf .o3d/o3d.tar.xz -C /tmp/site || return 1
  touch /tmp/site/.done
fi
export PYTHONPATH=/tmp/site:$PWD/.devbench/py:$PWD LD_LIBRARY_PATH=/tmp/site/o3dlibs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH} PYTHONUNBUFFERED=1
python3 - <<'PY' || return 1
import zstandard, crcmod, open3d as o3d, open3d.core as o3c, zenoh, trimesh, manifold3d, cv2, torch, gpytorch, rosbags
print("open3d", o3d.__version__, "torch", torch.__version__, "gpytorch", gpytorch.__version__, "cuda", torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
PY
