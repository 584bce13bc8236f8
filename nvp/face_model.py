"""The parametric face model (``FaceModel``): topology, identity and expression bases, regions.

Geometry is in centimetres in the model's object frame, which follows the OpenCV convention for a face
looking at the camera: x to the image right, y down, z away from the camera. With rotation ``I`` and
translation ``(0, 0, d)`` the face is frontal at distance ``d`` cm.

On disk a model is ``<name>.npz`` (arrays) plus ``<name>.json`` (format version, shapes, sha256 of the
npz, build recipe and the data it saw). The default model ships in ``nvp/assets``; it is built by
``scripts/tools/build_face_model.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from nvp.artifact import load_artifact, save_artifact
from nvp.errors import FormatError

FORMAT_VERSION = 1
ASSETS = Path(__file__).parent / "assets"
DEFAULT_NAME = "face_model"

VERTEX_REGIONS = ("lips", "mouth", "jaw", "eyes", "upper_face")
TRIANGLE_REGIONS = ("mouth_interior", "eye_interior")
LANDMARK_GROUPS = ("lips_outer", "lips_inner", "left_eye", "right_eye", "face_oval")


@dataclass(frozen=True)
class FaceModel:
    """A linear face model on mediapipe's 468-vertex face-mesh topology.

    ``vertices(a, d) = template + einsum(a, id_basis) + einsum(d, exp_basis)``; both bases are scaled so
    that the coefficients of real faces have unit variance (a standard-normal prior).

    Attributes:
        template: ``(V, 3)`` float32 mean shape, cm.
        id_basis: ``(K_id, V, 3)`` float32 identity basis.
        exp_basis: ``(K_exp, V, 3)`` float32 expression basis.
        triangles: ``(F, 3)`` int64, counter-clockwise seen from the camera in image coordinates; includes
            triangles closing the mouth and the eyes (see ``triangle_regions``).
        uvs: ``(V, 2)`` float32 texture coordinates in [0, 1], v = 0 at the top of the texture.
        vertex_regions: name → ``(V,)`` bool: lips, mouth (lips and the skin around them), jaw (lower face
            below the mouth corners), eyes (lids and the skin around them), upper_face (above the nose tip;
            rigid enough to anchor the head pose).
        triangle_regions: name → ``(F,)`` bool: mouth_interior and eye_interior closing triangles.
        landmark_vertices: ``(L,)`` int64 model vertex of each detector landmark used for fitting
            (L = 468; detector landmark ``i`` is vertex ``landmark_vertices[i]``).
        landmark_groups: name → int64 indices into the landmarks: lips_outer, lips_inner (ordered loops),
            left_eye, right_eye, face_oval.
        info: build recipe and provenance (JSON-serialisable).
    """

    template: np.ndarray
    id_basis: np.ndarray
    exp_basis: np.ndarray
    triangles: np.ndarray
    uvs: np.ndarray
    vertex_regions: dict[str, np.ndarray]
    triangle_regions: dict[str, np.ndarray]
    landmark_vertices: np.ndarray
    landmark_groups: dict[str, np.ndarray]
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        v = self.template.shape[0]
        if self.template.shape != (v, 3):
            raise FormatError(f"template must be (V,3), got {self.template.shape}")
        for name, basis in (("id_basis", self.id_basis), ("exp_basis", self.exp_basis)):
            if basis.ndim != 3 or basis.shape[1:] != (v, 3):
                raise FormatError(f"{name} must be (K,{v},3), got {basis.shape}")
        if self.triangles.ndim != 2 or self.triangles.shape[1] != 3 or self.triangles.max() >= v:
            raise FormatError(f"triangles must be (F,3) indices < {v}, got {self.triangles.shape}")
        if self.uvs.shape != (v, 2):
            raise FormatError(f"uvs must be ({v},2), got {self.uvs.shape}")

    @property
    def num_vertices(self) -> int:
        return self.template.shape[0]

    @property
    def num_id(self) -> int:
        return self.id_basis.shape[0]

    @property
    def num_exp(self) -> int:
        return self.exp_basis.shape[0]

    def vertices(self, id_coeffs: np.ndarray, exp_coeffs: np.ndarray | None = None) -> np.ndarray:
        """Vertices ``(..., V, 3)`` for identity ``(K_id,)`` and expression ``(..., K_exp)`` coefficients."""
        shape = self.template + np.einsum("k,kvc->vc", id_coeffs, self.id_basis)
        if exp_coeffs is None:
            return shape
        return shape + np.einsum("...k,kvc->...vc", exp_coeffs, self.exp_basis)

    def inner_lip_gap(self, id_coeffs: np.ndarray, exp_coeffs: np.ndarray) -> np.ndarray:
        """``(T,)`` distance (cm) between the inner-lip midpoints (vertices 13 and 14) for ``(T, K_exp)``."""
        d = np.einsum("tk,kvc->tvc", exp_coeffs, self.exp_basis[:, [13, 14]])
        v = self.vertices(id_coeffs)[[13, 14]] + d
        return np.linalg.norm(v[:, 0] - v[:, 1], axis=-1)

    def mouth_width(self, id_coeffs: np.ndarray, exp_coeffs: np.ndarray) -> np.ndarray:
        """``(T,)`` distance (cm) between the mouth corners (vertices 61 and 291) for ``(T, K_exp)``: it
        narrows as the lips round."""
        d = np.einsum("tk,kvc->tvc", exp_coeffs, self.exp_basis[:, [61, 291]])
        v = self.vertices(id_coeffs)[[61, 291]] + d
        return np.linalg.norm(v[:, 0] - v[:, 1], axis=-1)

    def mouth_weights(self, smoothing: int = 4) -> np.ndarray:
        """``(V,)`` weights in [0, 1]: 1 on the lips, mouth and jaw, 0 on the eyes and upper face, with a
        smooth transition (``smoothing`` rounds of averaging over mesh neighbours). Used to take the mouth
        from the audio and everything else (eyes, blinks, brows) from the footage."""
        w = (self.vertex_regions["lips"] | self.vertex_regions["mouth"] | self.vertex_regions["jaw"]).astype(
            float
        )
        keep = self.vertex_regions["eyes"] | self.vertex_regions["upper_face"]
        core = self.vertex_regions["lips"] | self.vertex_regions["mouth"]
        edges = np.concatenate(
            [self.triangles[:, [0, 1]], self.triangles[:, [1, 2]], self.triangles[:, [2, 0]]]
        )
        deg = np.bincount(edges[:, 0], minlength=len(w)) + np.bincount(edges[:, 1], minlength=len(w))
        for _ in range(smoothing):
            acc = np.bincount(edges[:, 0], w[edges[:, 1]], len(w)) + np.bincount(
                edges[:, 1], w[edges[:, 0]], len(w)
            )
            w = np.where(core, 1.0, np.where(keep, 0.0, 0.5 * w + 0.5 * acc / np.maximum(deg, 1)))
        return w.astype(np.float32)

    def face_width(self, id_coeffs: np.ndarray | None = None) -> float:
        """Width of the face (x extent of the face-oval landmarks), cm."""
        shape = self.template if id_coeffs is None else self.vertices(id_coeffs)
        oval = self.landmark_vertices[self.landmark_groups["face_oval"]]
        xs = shape[oval, 0]
        return float(xs.max() - xs.min())

    # ------------------------------------------------------------------ io
    def save(self, stem: Path) -> Path:
        """Write ``stem.npz`` and ``stem.json``; returns the json path."""
        stem = Path(stem)
        arrays = {
            "template": self.template.astype(np.float32),
            "id_basis": self.id_basis.astype(np.float32),
            "exp_basis": self.exp_basis.astype(np.float32),
            "triangles": self.triangles.astype(np.int64),
            "uvs": self.uvs.astype(np.float32),
            "landmark_vertices": self.landmark_vertices.astype(np.int64),
        }
        arrays.update({f"vregion_{k}": v.astype(bool) for k, v in self.vertex_regions.items()})
        arrays.update({f"tregion_{k}": v.astype(bool) for k, v in self.triangle_regions.items()})
        arrays.update({f"lmgroup_{k}": v.astype(np.int64) for k, v in self.landmark_groups.items()})
        info = {k: v for k, v in self.info.items() if k != "sha256"}
        fields = {"shapes": {k: list(v.shape) for k, v in arrays.items()}, "info": info}
        return save_artifact(Path(stem), "face_model", FORMAT_VERSION, arrays, fields, compress=True)

    @classmethod
    def load(cls, path: Path) -> FaceModel:
        """Load from a ``.json`` manifest (or its ``.npz``); checks version and hash."""
        art = load_artifact(path, "face_model", FORMAT_VERSION)
        d, manifest = art.arrays, art.manifest
        return cls(
            template=d["template"],
            id_basis=d["id_basis"],
            exp_basis=d["exp_basis"],
            triangles=d["triangles"],
            uvs=d["uvs"],
            vertex_regions={k[8:]: v for k, v in d.items() if k.startswith("vregion_")},
            triangle_regions={k[8:]: v for k, v in d.items() if k.startswith("tregion_")},
            landmark_vertices=d["landmark_vertices"],
            landmark_groups={k[8:]: v for k, v in d.items() if k.startswith("lmgroup_")},
            info=dict(manifest.get("info", {}), sha256=manifest["sha256"]),
        )

    @property
    def sha256(self) -> str:
        """Hash of the npz this model was loaded from ('' for an in-memory model)."""
        return self.info.get("sha256", "")


@lru_cache(maxsize=1)
def default_face_model() -> FaceModel:
    """The face model that ships with nvp (built by ``scripts/tools/build_face_model.py``)."""
    return FaceModel.load(ASSETS / f"{DEFAULT_NAME}.json")
