"""Our matchers inside hloc's ``match_features``.

hloc loads a matcher as the one ``BaseModel`` subclass defined in the module
``hloc.matchers.<name>``. ``register()`` creates the module ``hloc.matchers.paraformer``
with such a class, so that hloc finds it without any file added to hloc::

    from hloc import match_features
    from paraformer.sfm import hloc_plugin

    hloc_plugin.register()
    match_features.main(hloc_plugin.confs["paraformer-xfeat"], pairs_path,
                        features=features_path, matches=matches_path)

The features must be XFeat's (64-d): ``paraformer.sfm.extract`` writes them in hloc's layout.
Needs torch and hloc (``pip install --no-deps`` hloc's source; see the README).
"""
from __future__ import annotations

import sys
import types
from typing import Any

MODULE = "hloc.matchers.paraformer"

#: Ready-made hloc match confs, one per shipped matcher.
confs = {
    name: {"output": f"matches-{name}", "model": {"name": "paraformer", "weights": name}}
    for name in ("paraformer-xfeat", "paraformer-u-xfeat")
}


def register() -> type:
    """Creates ``hloc.matchers.paraformer`` (idempotent) and returns its matcher class.

    The model conf takes ``weights`` (a pretrained name or a weights file, default
    ``paraformer-xfeat``) and ``num_threads`` (Rust threads, default all cores).
    """
    if MODULE in sys.modules:
        return sys.modules[MODULE].Paraformer
    try:
        import torch
        import hloc.matchers
        from hloc.utils.base_model import BaseModel
    except ImportError as e:
        raise ImportError(f"the hloc plug-in needs torch and hloc installed: {e}") from None

    from ..pipeline import load_matcher

    class Paraformer(BaseModel):
        """ParaFormer / ParaFormer-U (Rust core) as an hloc matcher."""

        default_conf = {"weights": "paraformer-xfeat", "num_threads": None}
        required_inputs = ["keypoints0", "keypoints1", "descriptors0", "descriptors1"]

        def _init(self, conf: dict) -> None:
            self.net = load_matcher(conf["weights"])

        def _forward(self, data: dict) -> dict:
            out_m, out_s = [], []
            for b in range(data["keypoints0"].shape[0]):
                feats = []
                for i in "01":
                    kpts = data[f"keypoints{i}"][b].detach().cpu().numpy()
                    size = (data[f"image_size{i}"][b].detach().cpu().numpy() if f"image_size{i}" in data
                            else data[f"image{i}"].shape[-1:-3:-1])
                    f = {"keypoints": kpts, "descriptors": data[f"descriptors{i}"][b].detach().cpu().numpy().T,
                         "image_size": size}
                    if f"scores{i}" in data:
                        f["scores"] = data[f"scores{i}"][b].detach().cpu().numpy()
                    feats.append(f)
                (res,) = self.net.match_many([tuple(feats)], num_threads=self.conf["num_threads"])
                out_m.append(torch.from_numpy(res["matches0"]))
                out_s.append(torch.from_numpy(res["matching_scores0"]))
            dev = data["keypoints0"].device
            return {"matches0": torch.stack(out_m).to(dev), "matching_scores0": torch.stack(out_s).to(dev)}

    Paraformer.__module__ = MODULE
    module: Any = types.ModuleType(MODULE, __doc__)
    module.Paraformer = Paraformer
    sys.modules[MODULE] = module
    setattr(hloc.matchers, "paraformer", module)
    return Paraformer
