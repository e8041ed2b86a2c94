# device set-up (sourced): wheels and the stripped open3d 0.19 CPU build into /tmp/site
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || return 1
tar xJf .o3d/o3d.tar.xz -C /tmp/site || return 1
export PYTHONPATH=/tmp/site:$PWD LD_LIBRARY_PATH=/tmp/site/o3dlibs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH} PYTHONUNBUFFERED=1
python3 - <<'PY' || return 1
import open3d as o3d, open3d.core as o3c, numpy as np, zenoh, trimesh, manifold3d, cv2, torch, gpytorch
print("open3d", o3d.__version__, "zenoh", zenoh.__version__ if hasattr(zenoh, "__version__") else "?", "torch", torch.__version__, "gpytorch", gpytorch.__version__, "cuda", torch.cuda.is_available())
vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32), attr_channels=((1), (1)), voxel_size=0.004, block_resolution=16, block_count=1000, device=o3c.Device("CPU:0"))
print("VoxelBlockGrid ok")
PY
