"""``PersonBundle``: everything ``nvp dub`` needs to make a person say new audio, in one folder.

Layout of a bundle folder::

    bundle.json        manifest (format, version, hashes, preset, file map, stage timings, input hash)
    target.mp4         the target footage (copied: the bundle is self-contained)
    tracked/           TrackedSequence of the footage
    style.{json,npz}   the person's talking style (person map + rest expression)
    renderer/          neural texture + networks (renderer weights and their manifest)

A bundle is built in ``<out>.partial/`` (its ``progress.json`` records the settings, the sha256 of the input
video and the finished stages, so an interrupted ``nvp fit`` resumes, and restarts when the input changed),
then published by an atomic swap: ``bundle.json`` is written into the partial folder, an older bundle at
``<out>`` is moved aside to ``<out>.replaced``, the partial folder is renamed to ``<out>`` and the old one
removed. A run killed anywhere in between leaves a state that the next ``nvp fit`` (:func:`recover`)
completes; loading a bundle only reads. nvp never deletes or moves a folder that it did not make:
``<out>`` must be missing, empty or a person bundle.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from nvp.artifact import LOAD_ERRORS, file_sha256, write_json
from nvp.errors import FormatError, NvpError

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
MEMBER_ARTIFACTS = {
    "tracked": ("tracked/tracked.json", "tracked_sequence"),
    "style": ("style.json", "person_map"),
    "renderer": ("renderer/renderer.json", "renderer"),
}
"""Bundle member → (manifest path in the bundle, artifact kind), checked on load of a bundle made before its
manifest recorded every file's checksum (which versions a member may have, its own loader checks)."""
MOUTHS = ("renderer/mouths.json", "mouth_bank")
"""The mouth bank (optional member of the renderer), checked like :data:`MEMBER_ARTIFACTS`."""


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
    def load(cls, root: str | Path, verify: bool = True) -> PersonBundle:
        """Open a bundle, checking its format, version, face-model hash and every member: present, and
        (``verify``, :meth:`check`) every file the manifest lists at the size and sha256 it records — a
        truncated, emptied or altered file is reported here, naming it, not as a crash later. Reading never
        changes the disk: an interrupted publish is finished by the next ``nvp fit`` (:func:`recover`)."""
        from nvp.face_model import default_face_model

        root = Path(root)
        js = root / MANIFEST
        if not js.exists():  # read only: the next nvp fit finishes an interrupted publish (recover)
            if is_bundle(partial_dir(root)) or is_bundle(replaced_dir(root)):
                hint = (
                    " (an nvp fit was interrupted while publishing it: run the same nvp fit again to finish)"
                )
            elif partial_dir(root).exists():
                hint = " (an interrupted nvp fit? run it again to resume)"
            else:
                hint = ""
            raise FormatError(f"{root} is not a person bundle: {MANIFEST} missing{hint}")
        m = _read_bundle_manifest(js)
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
                raise bundle.damaged(m["files"][key], "is missing")
        if verify:
            bundle.check()
        return bundle

    def damaged(self, part: str, what: str) -> FormatError:
        """The error for a damaged ``part`` (a path in the bundle): "the bundle is damaged: <part> …"."""
        return FormatError(f"{self.root}: the bundle is damaged: {part} {what}; run nvp fit again")

    def check(self) -> int:
        """Check every file the manifest lists (``checksums``: path in the bundle → bytes and sha256,
        recorded when the bundle was published) and return how many; raise :class:`FormatError` naming the
        first damaged one (missing, cut short, emptied or altered). Bundles made before nvp recorded
        checksums are checked member by member: each artifact's arrays at the size and sha256 its manifest
        records (the mouth bank included) and the target video against the input's sha256."""
        sums = self.manifest.get("checksums")
        if isinstance(sums, dict):
            for rel, facts in sums.items():
                self._check_file(rel, facts)
            return len(sums)
        members = dict(MEMBER_ARTIFACTS)
        if (self.root / MOUTHS[0]).exists():
            members["mouths"] = MOUTHS
        for rel, kind in members.values():
            js = self.root / rel
            try:
                m = json.loads(js.read_text())
            except LOAD_ERRORS as e:
                raise self.damaged(rel, f"(not an nvp manifest: {e})") from e
            if not isinstance(m, dict) or m.get("format") != f"nvp.{kind}":
                raise self.damaged(rel, f"(expected an nvp.{kind} manifest)")
            arrays = Path(rel).parent / Path(str(m.get("arrays", Path(rel).with_suffix(".npz").name))).name
            self._check_file(arrays.as_posix(), {k: m[k] for k in ("bytes", "sha256") if k in m})
        target = self.manifest.get("target", {})
        facts = {"bytes": target.get("bytes"), "sha256": self.manifest.get("input_sha256")}
        self._check_file(self.manifest["files"]["target"], {k: v for k, v in facts.items() if v})
        return len(members) * 2 + 1

    def _check_file(self, rel: str, facts: dict) -> None:
        f = self.root / rel
        if not f.is_file():
            raise self.damaged(rel, "is missing")
        size = f.stat().st_size
        if "bytes" in facts and size != facts["bytes"]:
            cut = " (cut short)" if size < facts["bytes"] else ""
            raise self.damaged(rel, f"has {size} bytes, the fit wrote {facts['bytes']}{cut}")
        if "sha256" in facts and file_sha256(f) != facts["sha256"]:
            raise self.damaged(rel, "is not the file the fit wrote (its sha256 differs)")


def checksums(folder: Path) -> dict[str, dict]:
    """Path in ``folder`` → ``{"bytes", "sha256"}`` of every file in it but the bundle's manifest, its
    progress record and hidden (temporary) files: what :meth:`PersonBundle.check` verifies."""
    sums = {}
    for f in sorted(folder.rglob("*")):
        if f.is_file() and f.name not in (MANIFEST, PROGRESS) and not f.name.startswith("."):
            sums[f.relative_to(folder).as_posix()] = {"bytes": f.stat().st_size, "sha256": file_sha256(f)}
    return sums


def _read_bundle_manifest(js: Path) -> dict:
    try:
        m = json.loads(js.read_text())
    except LOAD_ERRORS as e:
        raise FormatError(f"cannot read {js} (the bundle's manifest is damaged?): {e}") from e
    if not isinstance(m, dict) or m.get("format") != FORMAT:
        raise FormatError(
            f"{js}: expected format {FORMAT}, found {m.get('format') if isinstance(m, dict) else m}"
        )
    return m


def partial_dir(root: Path) -> Path:
    """Where a bundle is built before it is published."""
    return root.with_name(root.name + ".partial")


def replaced_dir(root: Path) -> Path:
    """Where an older bundle waits while a new one is published."""
    return root.with_name(root.name + ".replaced")


def is_bundle(path: Path) -> bool:
    """Whether ``path`` is a folder holding a person bundle's manifest (of any version)."""
    try:
        return path.is_dir() and _read_bundle_manifest(path / MANIFEST) is not None
    except FormatError:
        return False


def recover(root: Path) -> None:
    """Finish a publish that was interrupted (see the module docstring); a no-op otherwise."""
    root = Path(root)
    work, old = partial_dir(root), replaced_dir(root)
    publishing = is_bundle(work) and not (work / PROGRESS).exists()  # bundle.json written, not yet swapped
    if publishing and (not root.exists() or is_bundle(root)):
        if root.exists():
            if old.exists():
                shutil.rmtree(old)
            os.replace(root, old)
        os.replace(work, root)
    if old.exists() and is_bundle(root):
        shutil.rmtree(old)  # killed before the old bundle was removed
    elif old.exists() and not root.exists() and is_bundle(old):
        os.replace(old, root)  # killed after moving the old bundle aside, before the new one was ready


def enclosing_bundle(path: str | Path) -> Path | None:
    """The person bundle folder that holds ``path`` (its resolved path), or the folder a bundle is being
    built in or replaced from; None when ``path`` is in no such folder."""
    for folder in Path(path).resolve().parents:
        building = folder.name.endswith(".partial") and (folder / PROGRESS).is_file()
        if building or is_bundle(folder):
            return folder
    return None


def check_output_place(output: str | Path, inputs: tuple[str | Path | None, ...] = ()) -> Path:
    """Refuse an output path that would write over data it does not own: one of the ``inputs`` (compared
    as resolved paths and as files, so links and ``..`` do not hide it), a path inside an input folder or
    a folder holding an input, or a path inside a person bundle (whose files ``nvp fit`` made and
    ``nvp info`` checks). ``None`` inputs are skipped. Returns ``output`` as a Path."""
    out = Path(output)
    where = out.resolve()
    bundle = enclosing_bundle(where)
    if bundle is not None:
        raise NvpError(
            f"the output {out} is inside the person bundle {bundle}; nvp keeps a bundle as nvp fit made it "
            "(write the output elsewhere)"
        )
    for given in inputs:
        if given is None:
            continue
        inp = Path(given)
        here = inp.resolve()
        same = where == here or (out.exists() and inp.exists() and os.path.samefile(out, inp))
        if same:
            raise NvpError(f"the output {out} is also an input ({inp}); choose another output name")
        if here in where.parents:
            raise NvpError(f"the output {out} is inside the input folder {inp}; choose a place outside it")
        if where in here.parents:
            raise NvpError(f"the output {out} holds the input {inp}; choose another output name")
    return out


def check_output_folder(root: Path, inputs: tuple[Path, ...] = ()) -> None:
    """Refuse an output that nvp would have to delete or overwrite without having made it: a file, one of
    the ``inputs`` or a folder holding one, a folder inside a person bundle, or a folder that is neither
    empty nor a person bundle."""
    root = Path(root)
    for p in inputs:
        if root.resolve() == Path(p).resolve():
            raise NvpError(f"the output {root} is the input video; choose a new folder for the person bundle")
    check_output_place(root, inputs)
    if root.exists() and not root.is_dir():
        raise NvpError(f"the output {root} is a file; a person bundle is a folder (choose a new name)")
    if root.is_dir() and any(root.iterdir()) and not is_bundle(root):
        raise NvpError(
            f"the output folder {root} is not empty and is not a person bundle; nvp will not overwrite it "
            "(choose a new or empty folder)"
        )
    work = partial_dir(root)
    if work.exists() and not (work / PROGRESS).exists() and not is_bundle(work):
        raise NvpError(f"{work} exists and was not made by nvp fit; move it away first")


class BundleBuilder:
    """Builds a bundle in ``<root>.partial`` with resumable stages, then publishes it atomically.

    ``config``: the settings a resume must share; ``input_sha256``: the input video's hash; ``version``: the
    nvp that fits (:func:`nvp.provenance.code_version`) — a partial bundle made from another input or by
    another nvp is discarded and the fit starts again (``restarted`` then says why: "of another video",
    "made by nvp 0.1.0+g…"; empty otherwise).
    """

    def __init__(
        self, root: str | Path, config: dict, input_sha256: str | None = None, version: str | None = None
    ) -> None:
        self.root = Path(root)
        check_output_folder(self.root)
        recover(self.root)
        self.work = partial_dir(self.root)
        self._progress_path = self.work / PROGRESS
        self.progress = self._read_progress()
        self.restarted = ""
        if input_sha256 is not None and self.progress.get("input_sha256", input_sha256) != input_sha256:
            shutil.rmtree(self.work)  # an nvp-made partial bundle of another video: start again
            self.progress, self.restarted = {}, "of another video"
        elif version is not None and self.progress and self.progress.get("nvp") != version:
            shutil.rmtree(self.work)  # work another nvp left (its stages may differ): start again
            self.progress, self.restarted = {}, f"made by nvp {self.progress.get('nvp', 'before 0.1.0+g')}"
        if self.progress.get("config", config) != config:
            changed = sorted(k for k in config if self.progress["config"].get(k) != config[k])
            raise FormatError(
                f"{self.work} holds an interrupted fit with other settings ({', '.join(changed)}); "
                "delete it or use the same settings to resume"
            )
        self.work.mkdir(parents=True, exist_ok=True)
        self.progress["config"] = config
        if input_sha256 is not None:
            self.progress["input_sha256"] = input_sha256
        if version is not None:
            self.progress["nvp"] = version
        self._save()

    def _read_progress(self) -> dict:
        if not self._progress_path.exists():
            return {}
        try:
            return json.loads(self._progress_path.read_text())
        except LOAD_ERRORS:
            return {}  # damaged by a crash while it was replaced: the stages are redone

    def path(self, key: str) -> Path:
        return self.work / FILES[key]

    def done(self, stage: str) -> bool:
        return stage in self.progress.get("stages", {})

    def mark_done(self, stage: str, **facts) -> None:
        self.progress.setdefault("stages", {})[stage] = facts
        self._save()

    def _save(self) -> None:
        write_json(self._progress_path, self.progress)

    def publish(self, manifest: dict) -> PersonBundle:
        """Write ``bundle.json`` and swap the folder into place (replacing an older bundle)."""
        m = {"format": FORMAT, "version": FORMAT_VERSION, "files": dict(FILES), **manifest}
        m["stages"] = self.progress.get("stages", {})
        m["input_sha256"] = self.progress.get("input_sha256")
        m["config"] = self.progress.get("config", {})
        m.setdefault("target", {})["bytes"] = self.path("target").stat().st_size
        m["checksums"] = checksums(self.work)
        write_json(self.work / MANIFEST, m)
        self._progress_path.unlink()  # from here on the partial folder is a complete bundle
        recover(self.root)  # the swap; a run killed in it is finished by the next one the same way
        return PersonBundle(self.root, m)


def check_replacing(root: Path, input_sha256: str) -> None:
    """Refuse to replace the person bundle at ``root`` when it was fitted from another video (the
    ``input_sha256`` of this fit differs from the one it recorded); ``nvp fit --force`` skips this."""
    root = Path(root)
    if not is_bundle(root):
        return
    m = _read_bundle_manifest(root / MANIFEST)
    if m.get("input_sha256") == input_sha256:
        return  # the same video with other settings: fitting it again is what the user asks for
    t = m.get("target") if isinstance(m.get("target"), dict) else {}
    source = Path(str(t.get("source", "an unknown video"))).name
    length = f", {t['duration_s']:.0f} s" if isinstance(t.get("duration_s"), (int, float)) else ""
    raise NvpError(
        f"{root} is the person bundle of another video ({source}{length}); this fit would replace it: "
        "give --force to replace it, or choose another folder"
    )


def finished_bundle(root: Path, config: dict, input_sha256: str) -> PersonBundle | None:
    """The bundle at ``root`` if it is complete, undamaged and was fitted from the same input with the
    same settings (so fitting again would only repeat the work); None otherwise."""
    try:
        b = PersonBundle.load(root)
    except NvpError:
        return None
    same = b.manifest.get("input_sha256") == input_sha256 and b.manifest.get("config") == config
    return b if same else None


def input_hash(path: Path) -> str:
    """sha256 of an input file (what a resume must match)."""
    return file_sha256(Path(path))
