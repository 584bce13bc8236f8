"""Persisting a person map and predicting a person's expressions from new audio.

``predict_expressions`` is the audio half of ``nvp dub``: speech features → generic network → person map
→ expression coefficients ``(T, K_exp)`` at the target's frame rate.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nvp.audio2exp import Audio2ExpressionNet, PersonMap
from nvp.errors import FormatError

FORMAT_VERSION = 1
ASSETS = Path(__file__).parent / "assets"


@dataclass(frozen=True)
class PersonStyle:
    """A person map plus what it was made with (the feature kind and the generic network's hash)."""

    person_map: PersonMap
    feature_kind: str
    audio2exp_sha256: str
    info: dict

    def save(self, path: Path) -> Path:
        """Write ``path`` (.npz) and its ``.json`` manifest atomically."""
        path = Path(path).with_suffix(".npz")
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.stem}.tmp.npz")
        np.savez(tmp, matrix=self.person_map.matrix, bias=self.person_map.bias)
        os.replace(tmp, path)
        manifest = {
            "format": "nvp.person_map",
            "version": FORMAT_VERSION,
            "arrays": path.name,
            "feature_kind": self.feature_kind,
            "audio2exp_sha256": self.audio2exp_sha256,
            "info": self.info,
        }
        js = path.with_suffix(".json")
        tmpj = path.with_name(f".{path.stem}.tmp.json")
        tmpj.write_text(json.dumps(manifest, indent=2) + "\n")
        os.replace(tmpj, js)
        return js

    @classmethod
    def load(cls, path: Path) -> PersonStyle:
        js = Path(path).with_suffix(".json")
        try:
            m = json.loads(js.read_text())
            if m.get("format") != "nvp.person_map" or m.get("version") != FORMAT_VERSION:
                raise FormatError(
                    f"{js}: expected nvp.person_map version {FORMAT_VERSION}, found "
                    f"{m.get('format')} version {m.get('version')}"
                )
            with np.load(js.parent / m["arrays"]) as z:
                pm = PersonMap(matrix=z["matrix"], bias=z["bias"])
        except (OSError, ValueError, KeyError) as e:
            raise FormatError(f"cannot read person map {js}: {e}") from e
        return cls(pm, m["feature_kind"], m["audio2exp_sha256"], m.get("info", {}))


def default_audio2exp(kind: str = "phonemes") -> tuple[Audio2ExpressionNet, dict]:
    """The generic network that ships with nvp for a feature kind, and its manifest."""
    from nvp.train_audio2exp import load_net

    path = ASSETS / f"audio2exp_{kind}.json"
    if not path.exists():
        raise FormatError(f"no shipped Audio2ExpressionNet for features '{kind}' ({path} missing)")
    return load_net(path)


def predict_expressions(
    audio: np.ndarray,
    sample_rate: int,
    fps: float,
    style: PersonStyle,
    net: Audio2ExpressionNet,
    num_frames: int | None = None,
) -> np.ndarray:
    """Expression coefficients ``(T, K_exp)`` for mono float32 audio, at ``fps`` video frames per second."""
    from nvp.audio_features import extract_features, frame_windows, speaker_normalized
    from nvp.train_audio2exp import audio_expressions

    feats = speaker_normalized(extract_features(audio, sample_rate, kind=style.feature_kind))
    windows = frame_windows(feats, fps, num_frames=num_frames).astype(np.float32)
    return style.person_map.apply(audio_expressions(net, windows))
