"""``PersonBundle``: everything ``nvp dub`` needs to make a person say new audio, in one folder.

Layout of a bundle folder::

    bundle.json        manifest (format, version, hashes, preset, file map, stage timings)
    target.mp4         the target footage (copied: the bundle is self-contained)
    tracked/           TrackedSequence of the footage
    style.{json,npz}   the person's talking style (person map + rest expression)
    renderer/          neural texture + networks (renderer weights and their manifest)

A bundle is built in ``<out>.partial/`` and renamed to ``<out>`` when every stage is done, so a folder
with a ``bundle.json`` is always complete; an interrupted ``nvp fit`` resumes from the ``.partial``
folder, skipping the stages already recorded in its ``progress.json``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from nvp.errors import FormatError

FORMAT = "nvp.person_bundle"
FORMAT_VERSION = 1
MANIFEST = "bundle.json"
PROGRESS = "progress.json"
FILES = {
    "target": "target.mp4",
    "tracked": "tracked",
    "style": "style.json",
    "renderer": "renderer",
}


@dataclass(frozen=True)
class PersonBundle:
    """A finished bundle on disk.

    Attributes:
        root: the bundle folder.
        manifest: the parsed ``bundle.json`` (format, version, nvp version, face-model and
            Audio2ExpressionNet hashes, feature kind, preset, target video facts, stage timings).
    """

    root: Path
    manifest: dict

    def path(self, key: str) -> Path:
        """Path of a bundle member: ``target``, ``tracked``, ``style`` or ``renderer``."""
        return self.root / self.manifest["files"][key]

    @classmethod
    def load(cls, root: str | Path) -> PersonBundle:
        """Open a bundle, checking its format, version, members and face-model hash."""
        from nvp.face_model import default_face_model

        root = Path(root)
        js = root / MANIFEST
        if not js.exists():
            hint = " (an interrupted nvp fit? run it again to resume)" if _partial(root).exists() else ""
            raise FormatError(f"{root} is not a person bundle: {MANIFEST} missing{hint}")
        try:
            m = json.loads(js.read_text())
        except (OSError, ValueError) as e:
            raise FormatError(f"cannot read {js}: {e}") from e
        if m.get("format") != FORMAT:
            raise FormatError(f"{js}: expected format {FORMAT}, found {m.get('format')}")
        if m.get("version") != FORMAT_VERSION:
            raise FormatError(
                f"{js}: bundle version {m.get('version')} is not supported by this nvp "
                f"(expects {FORMAT_VERSION}); run nvp fit again"
            )
        if m.get("face_model_sha256") != default_face_model().sha256:
            raise FormatError(f"{root} was made with another face model; run nvp fit again")
        bundle = cls(root, m)
        for key in FILES:
            if not bundle.path(key).exists():
                raise FormatError(f"{root} is incomplete: {m['files'][key]} missing")
        return bundle


def _partial(root: Path) -> Path:
    return root.with_name(root.name + ".partial")


class BundleBuilder:
    """Builds a bundle in ``<root>.partial`` with resumable stages, then publishes it atomically."""

    def __init__(self, root: str | Path, config: dict) -> None:
        self.root = Path(root)
        self.work = _partial(self.root)
        self.work.mkdir(parents=True, exist_ok=True)
        self._progress_path = self.work / PROGRESS
        self.progress = json.loads(self._progress_path.read_text()) if self._progress_path.exists() else {}
        if self.progress.get("config", config) != config:
            changed = sorted(k for k in config if self.progress["config"].get(k) != config[k])
            raise FormatError(
                f"{self.work} holds an interrupted fit with other settings ({', '.join(changed)}); "
                "delete it or use the same settings to resume"
            )
        self.progress["config"] = config
        self._save()

    def path(self, key: str) -> Path:
        return self.work / FILES[key]

    def done(self, stage: str) -> bool:
        return stage in self.progress.get("stages", {})

    def mark_done(self, stage: str, **facts) -> None:
        self.progress.setdefault("stages", {})[stage] = facts
        self._save()

    def _save(self) -> None:
        tmp = self.work / f".{PROGRESS}.tmp"
        tmp.write_text(json.dumps(self.progress, indent=2) + "\n")
        os.replace(tmp, self._progress_path)

    def publish(self, manifest: dict) -> PersonBundle:
        """Write ``bundle.json`` and move the folder to its final name (replacing an older bundle)."""
        m = {"format": FORMAT, "version": FORMAT_VERSION, "files": dict(FILES), **manifest}
        m["stages"] = self.progress.get("stages", {})
        (self.work / MANIFEST).write_text(json.dumps(m, indent=2) + "\n")
        self._progress_path.unlink()
        if self.root.exists():
            old = self.root.with_name(self.root.name + ".old")
            os.replace(self.root, old)
            os.replace(self.work, self.root)
            import shutil

            shutil.rmtree(old)
        else:
            os.replace(self.work, self.root)
        return PersonBundle(self.root, m)
