import numpy as np
from typer.testing import CliRunner

import monoloc.server.vision.default_vocab as default_vocab
from monoloc.server.cli import vocab_app
from monoloc.server.vision.vocabulary import VocabularyConfig, load_vocabulary, train_vocabulary


def test_vocab_train_writes_a_loadable_vocabulary(tmp_path, monkeypatch):
    seen = {}

    def small_recipe(vocabulary=VocabularyConfig()):
        # The real recipe takes ~6 s; the CLI only has to pass the options and save.
        seen["config"] = vocabulary
        rng = np.random.default_rng(vocabulary.seed)
        descriptors = rng.integers(0, 256, size=(2000, 32)).astype(np.uint8)
        return train_vocabulary(descriptors, vocabulary, description="test recipe")

    monkeypatch.setattr(default_vocab, "train_default_vocabulary", small_recipe)
    out = tmp_path / "sub" / "vocab.npz"
    result = CliRunner().invoke(vocab_app, ["train", "--out", str(out), "--seed", "3"])
    assert result.exit_code == 0, result.output
    assert seen["config"].seed == 3
    vocabulary = load_vocabulary(out)
    assert vocabulary.version in result.output
    assert vocabulary.description == "test recipe"
