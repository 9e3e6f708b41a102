"""Pure vision core of the map server: ORB features, vocabulary, VLAD, binary codes,
Hamming matching, PnP and pose hypotheses (METHOD.md sections 2-6).

Every function takes arrays and a frozen config and returns arrays; the only file I/O is
reading and writing vocabularies (``vocabulary.py``).
"""

from monoloc.server.vision.binary_code import CODE_BYTES, vlad_binary_code
from monoloc.server.vision.features import Features, OrbConfig, extract_features
from monoloc.server.vision.hypothesis import compose_hypothesis, planar_hypothesis
from monoloc.server.vision.matching import (
    MatchConfig,
    match_against_references,
    match_descriptors,
    match_descriptors_bruteforce,
)
from monoloc.server.vision.pnp import PnpConfig, RelativePose, estimate_relative_pose
from monoloc.server.vision.vlad import VLAD_DIM, compute_vlad, compute_vlad_batch, vlad_distance
from monoloc.server.vision.vocabulary import (
    Vocabulary,
    VocabularyConfig,
    load_default_vocabulary,
    load_vocabulary,
    save_vocabulary,
    train_vocabulary,
    vocabulary_hash,
)

__all__ = [
    "CODE_BYTES",
    "VLAD_DIM",
    "Features",
    "MatchConfig",
    "OrbConfig",
    "PnpConfig",
    "RelativePose",
    "Vocabulary",
    "VocabularyConfig",
    "compose_hypothesis",
    "compute_vlad",
    "compute_vlad_batch",
    "estimate_relative_pose",
    "extract_features",
    "load_default_vocabulary",
    "load_vocabulary",
    "match_against_references",
    "match_descriptors",
    "match_descriptors_bruteforce",
    "planar_hypothesis",
    "save_vocabulary",
    "train_vocabulary",
    "vlad_binary_code",
    "vlad_distance",
    "vocabulary_hash",
]
