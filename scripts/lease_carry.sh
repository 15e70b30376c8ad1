#!/usr/bin/env bash
# Build .lease/: what a lent GPU machine lacks to render the twin and train (scripts/lease_train.sh installs it).
#
# The machine (device README/KINDS.md) has Python 3.12, torch, numpy, scipy, OpenCV, rich, typer, safetensors,
# matplotlib and scikit-image, and no package index. The twin's renderer needs open3d, and the project pydantic
# and triangle. open3d's CUDA wheel does not fit what a command may carry (64 MiB with the working tree: its
# library alone is 89 MB and more under xz), its CPU build does: the renderer casts rays on the CPU anyway.
#
#   bash scripts/lease_carry.sh          # then: run(command="bash scripts/lease_train.sh", carry=[".lease"], ...)
#
# Checks itself on this host: the carried package imports in a Python 3.12 of pyenv's (when there is one, with
# numpy from PyPI) and casts a ray; the working tree plus .lease must fit in the 64 MiB that travel.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${LEASE_PY:-3.12}
O3D=${LEASE_OPEN3D:-open3d-cpu==0.20.0}
PIP=${PIP:-.venv/bin/python -m pip}
# the versions this venv runs, for the machine's Python
WHEELS="pydantic==2.14.4 pydantic_core==2.50.5 annotated-types==0.8.0 typing-inspection==0.4.5 triangle==20250106"
plat=""
for n in 17 24 27 28 31 34 35; do plat="$plat --platform manylinux_2_${n}_x86_64"; done
plat="$plat --platform manylinux2014_x86_64"
dl="$PIP download -q --no-deps --only-binary=:all: --python-version $PY --implementation cp $plat"

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
rm -rf .lease && mkdir -p .lease/whl "$work/lib"
$dl -d .lease/whl $WHEELS
# triangle's wheel ships 3.9 MB of example meshes (triangle/data/*: read only by triangle.get_data, which the twin
# never calls): repacked without them (and their RECORD lines) so the carry fits beside the working tree
.venv/bin/python - .lease/whl/triangle-*.whl <<'PY'
import sys, zipfile
path = sys.argv[1]
with zipfile.ZipFile(path) as src:
    items = [(i, src.read(i)) for i in src.infolist() if not i.filename.startswith("triangle/data/")]
with zipfile.ZipFile(path, "w") as dst:
    for info, data in items:
        if info.filename.endswith(".dist-info/RECORD"):
            data = b"".join(line for line in data.splitlines(keepends=True) if not line.startswith(b"triangle/data/"))
        dst.writestr(info, data, compress_type=zipfile.ZIP_DEFLATED, compresslevel=9)
PY
$dl -d "$work" "$O3D"

# open3d, pruned to what the twin imports (open3d.ml is imported by open3d itself: kept; its TF/torch ops, GUI
# resources and examples are not loaded by ray casting)
(cd "$work" && unzip -q ./*.whl 'open3d/*')
rm -rf "$work"/open3d/{resources,examples,labextension,nbextension,agent_skills,tools}
rm -f "$work"/open3d/open3d_tf_ops.so "$work"/open3d/open3d_torch_ops.so
# the Open3D-ML models and their TF/torch wrappers (open3d.ml loads them only on request) and the type stubs: never
# loaded by ray casting, and the carry must fit 64 MiB beside the working tree (session 50: 0.7 MiB over without)
rm -rf "$work"/open3d/_ml3d "$work"/open3d/ml/tf "$work"/open3d/ml/torch
find "$work"/open3d -name "*.pyi" -delete
# open3d.visualization imports its plotly/dash viewer at import time; the machine has neither and the twin never
# draws: the carried copy names what is missing if it is ever called
cat > "$work"/open3d/visualization/draw_plotly.py <<'STUB'
"""Replaced in gearscan's GPU-lease carry (scripts/lease_carry.sh): plotly and dash are not carried."""


def _not_carried(*args, **kwargs):
    raise ImportError("open3d.visualization.draw_plotly: plotly and dash are not in gearscan's lease carry")


get_plotly_fig = draw_plotly = draw_plotly_server = _not_carried
STUB
tar -C "$work" -cf - open3d | xz -9 -T2 > .lease/open3d.tar.xz

# the shared libraries libOpen3D links against beyond glibc and the C++ runtime, from this host (older than the
# machine's, so they run there); lease_train.sh puts only those the machine lacks on LD_LIBRARY_PATH
ldd "$work"/open3d/libOpen3D.so.* | awk '$3 ~ /^\// {print $1, $3}' | while read -r name path; do
  case "$name" in
    libc.so*|libm.so*|libstdc++*|libgcc_s*|libpthread*|libdl.so*|librt.so*|ld-linux*|libtbb*) ;;
    *) cp -L "$path" "$work/lib/$name" ;;
  esac
done
tar -C "$work" -cf - lib | xz -9 > .lease/lib.tar.xz

# self-check in a Python like the machine's (pyenv's, if present): the pruned package imports and casts a ray
pyenv_py=$(ls -d /root/.pyenv/versions/"$PY"*/bin/python3 2>/dev/null | head -1 || true)
if [ -n "$pyenv_py" ]; then
  venv="$work/venv"
  "$pyenv_py" -m venv "$venv"
  "$venv/bin/python" -m pip install -q numpy typing_extensions  # both on the machine already
  "$venv/bin/python" -m pip install -q --no-index --no-deps --target "$work/site" .lease/whl/*.whl
  tar -C "$work/site" -xJf .lease/open3d.tar.xz
  PYTHONPATH="$work/site" "$venv/bin/python" - <<'EOF'
import numpy as np
import open3d as o3d
import pydantic, triangle  # noqa: F401
mesh = o3d.geometry.TriangleMesh.create_box()
scene = o3d.t.geometry.RaycastingScene()
scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
hit = scene.cast_rays(o3d.core.Tensor(np.array([[0.5, 0.5, -1, 0, 0, 1]], np.float32)))["t_hit"].numpy()
assert abs(hit[0] - 1.0) < 1e-6, hit
print(f"lease carry: open3d {o3d.__version__} imports and casts in Python {__import__('sys').version.split()[0]}")
EOF
else
  echo "lease carry: no pyenv Python $PY here: not self-checked" >&2
fi

# what the device tool sends: tracked and untracked-not-ignored files (summed over every du batch xargs makes)
tree=$(git ls-files -co --exclude-standard -z | xargs -0 du -cb 2>/dev/null | awk -F'\t' '$2 == "total" {s += $1} END {print s + 0}')
carry=$(du -sb .lease | cut -f1)
total=$((tree + carry))
echo "lease carry: .lease $((carry / 1048576)) MiB + working tree $((tree / 1048576)) MiB = $((total / 1048576)) MiB (limit 64)"
if [ "$total" -gt $((64 * 1048576)) ]; then
  echo "lease carry: over the 64 MiB a command may carry (session 50 took v5's weights out of the tree for this; next:"\
       "weights no product path loads, or only the libraries the machine lacked, which the last lease.log lists)" >&2
  exit 1
fi
