"""From a photo collection to a COLMAP reconstruction, with hloc-compatible files.

>>> from paraformer import sfm                                                # doctest: +SKIP
>>> rec = sfm.reconstruct("photos/", "out/", matcher="paraformer-xfeat")      # doctest: +SKIP

Stages, each usable alone and resumable: ``extract`` (XFeat → ``features.h5``), pairs
(``pairs_exhaustive``, ``pairs_sequential``, ``read_pairs`` / ``write_pairs``),
``match_pairs`` (``match_many`` → ``matches.h5``) and ``reconstruct_from_files`` (pycolmap:
database, geometric verification, incremental mapping). The files follow hloc's layouts,
so hloc's files work here and ours in hloc; ``paraformer.sfm.hloc_plugin`` makes the
matchers usable from hloc's ``match_features``. Needs ``pip install 'paraformer[sfm]'``
(h5py, pycolmap, tqdm); ``backend="ray"`` needs ``paraformer[ray]``.
"""
from .extract_features import extract, list_images
from .io import names_to_pair, read_pairs, write_pairs
from .match_features import match_pairs
from .pairs import pairs_exhaustive, pairs_sequential
from .reconstruction import PYCOLMAP_SUPPORTED, reconstruct, reconstruct_from_files

__all__ = ["extract", "list_images", "match_pairs", "pairs_exhaustive", "pairs_sequential", "read_pairs",
           "write_pairs", "names_to_pair", "reconstruct", "reconstruct_from_files", "PYCOLMAP_SUPPORTED"]
