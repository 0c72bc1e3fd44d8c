"""Deformable superquadrics (Terzopoulos & Metaxas, PAMI 1991): fit point clouds and images.

``fit`` takes an (N, 3) array and the keywords of ``dsq fit``'s flags, and fits the cloud exactly
as ``dsq fit`` fits the same points; ``track`` follows an object through depth frames as
``dsq track`` does. Every fit releases the GIL, so threads fit in parallel. Bad
input raises ``ValueError`` with the one-line message ``dsq`` prints.
"""

from os import PathLike
from typing import Any, Literal, Sequence, TypedDict

import numpy as np
import numpy.typing as npt

__version__: str

class Residuals(TypedDict):
    """Point-to-surface distances as fractions of the bounding-box diagonal."""

    mean: float
    rms: float
    p95: float
    max: float
    diagonal: float

class FitResult:
    """A superquadric (and its membrane) fitted to a point cloud."""

    @property
    def translation(self) -> list[float]:
        """The model frame's origin c, in data units."""
    @property
    def rotation(self) -> list[float]:
        """The rotation as a unit quaternion [w, x, y, z] (the paper's [s, v1, v2, v3])."""
    @property
    def rotation_matrix(self) -> npt.NDArray[np.float64]:
        """The rotation as a 3 x 3 matrix (model frame to data frame)."""
    @property
    def a(self) -> float:
        """The scale a, in data units."""
    @property
    def aspect(self) -> list[float]:
        """The aspect ratios a1, a2, a3."""
    @property
    def epsilon(self) -> list[float]:
        """The squareness exponents e1 (along z) and e2 (about z)."""
    @property
    def taper(self) -> list[float]:
        """The tapering (t_x, t_y); zero unless ``taper=True``."""
    @property
    def bend(self) -> list[float]:
        """The bending (b_x, b_y); zero unless ``bend=True``."""
    @property
    def residuals(self) -> Residuals:
        """Point-to-surface distances over the bounding-box diagonal."""
    @property
    def converged(self) -> bool:
        """Whether the fit came to rest before its step cap."""
    @property
    def steps(self) -> int:
        """Steps (or solver iterations) taken."""
    @property
    def nodes(self) -> int:
        """The membrane's node count."""
    @property
    def solver(self) -> Literal["solved", "dynamics"]:
        """Which solver ran."""
    @property
    def noise(self) -> float | None:
        """The noise the points show (fraction of the diagonal), when the stiffness came from it."""
    def mesh(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
        """The fitted closed surface: vertices (V, 3) and triangles (F, 3)."""
    def surface_points(self, n: int, seed: int = 0) -> npt.NDArray[np.float64]:
        """``n`` points on the fitted surface, uniform by area, as an (n, 3) array."""
    def to_dict(self) -> dict[str, object]:
        """The parameters as ``dsq fit --out-params`` writes them."""

class ImagePart:
    """One part fitted to an image, in the image plane's frame (the image's longer side spans
    [-0.5, 0.5], y up)."""

    @property
    def translation(self) -> list[float]: ...
    @property
    def rotation(self) -> list[float]: ...
    @property
    def a(self) -> float: ...
    @property
    def aspect(self) -> list[float]: ...
    @property
    def epsilon(self) -> list[float]: ...
    @property
    def converged(self) -> bool: ...
    @property
    def steps(self) -> int: ...
    @property
    def stopped(self) -> str | None:
        """Why the part was stopped (it grew without bound or left the image), or None."""
    @property
    def outline(self) -> tuple[float, float]:
        """The mean image potential along the outline before and after (1: a strong edge)."""
    def mesh(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]: ...

def fit(
    points: npt.ArrayLike,
    *,
    global_only: bool = False,
    solver: Literal["solved", "lm", "dynamics"] = "solved",
    paper_forces: bool = False,
    robust: bool = False,
    plane: bool = False,
    switch: bool = False,
    similar: bool = False,
    migrate: bool = False,
    taper: bool = False,
    bend: bool = False,
    outliers: float = 0.2,
    nodes: int | None = None,
    k: int | None = None,
    w0: float | None = None,
    w1: float | Literal["auto"] | None = None,
    beta: float | None = None,
    max_steps: int | None = None,
    reassign: int | None = None,
    implicit_local: float | None = None,
) -> FitResult:
    """Fits a deformable superquadric to an (N, 3) array of points with ``dsq fit``'s defaults
    for a cloud; each keyword is the flag of the same name (docs/cli.md)."""

class PartsResult:
    """A whole object fitted as parts."""

    @property
    def parts(self) -> list[FitResult]:
        """Each part's fit, as ``fit`` returns it."""
    @property
    def owner(self) -> npt.NDArray[np.int64]:
        """The part of each point (the one whose surface is nearest), an (N,) array."""
    @property
    def joints(self) -> list[tuple[int, int, tuple[float, float, float]]]:
        """The joints between parts that touch: (part i, part j, where they touch)."""
    @property
    def explained(self) -> float:
        """The fraction of the points within reach of the nearest part (where coding a point as
        an outlier would be cheaper)."""
    @property
    def part_explained(self) -> list[float]:
        """For each part, the fraction of its points within reach of it."""
    def __len__(self) -> int: ...

def fit_parts(
    points: npt.ArrayLike,
    parts: Literal["auto"] | int = "auto",
    max_parts: int | None = None,
    **options: Any,
) -> PartsResult:
    """Fits a whole object: the points split into parts as ``dsq fit --parts`` splits a cloud,
    ``"auto"`` (at most ``max_parts``, default 24) or a count; ``options`` are ``fit``'s keywords."""

def load_points(path: str | PathLike[str], mesh_samples: int = 10000) -> npt.NDArray[np.float64]:
    """The points of an OBJ or PLY file as an (N, 3) array: its vertices, or, when the file has
    faces, ``mesh_samples`` points spread uniformly by area over its surface."""

def fit_image(
    image: npt.ArrayLike,
    parts: Sequence[Sequence[float]],
    *,
    global_only: bool = False,
    solver: Literal["solved", "lm", "dynamics"] = "solved",
    sigma: float = 2.0,
    band: float = 0.2,
    region: float = 0.0,
    paper_band: bool = False,
    free_depth: bool = False,
    fix_epsilon: bool = False,
    nodes: int | None = None,
    k: int | None = None,
    w0: float | None = None,
    w1: float | None = None,
    beta: float | None = None,
    max_steps: int | None = None,
) -> list[ImagePart]:
    """Fits one part per entry of ``parts`` (eight pixel coordinates: both ends of the major
    axis, then of the minor) to an (H, W) grey or (H, W, 3) colour image, as
    ``dsq fit --image`` does: solved for each part's rest by default; ``band``, ``region``,
    ``paper_band``, ``free_depth``, ``w0``, ``w1``, ``beta`` and ``max_steps`` set the paper's
    dynamics and need ``solver="dynamics"``."""

class Track:
    """A track in progress: iterating it tracks the next frame and gives ``dsq track``'s line
    for it as a dict (``frame``, ``translation``, ``rotation`` [s, v1, v2, v3], ``a``, ``a1``,
    ``a2``, ``a3``, ``e1``, ``e2``, ``lost``, ``points``, ``inliers``, ``free_rays``, ``rms``,
    ``iterations``, and ``file`` for a path), without its time."""

    def __iter__(self) -> Track: ...
    def __next__(self) -> dict[str, Any]: ...

def track(
    frames: Any,
    intrinsics: str | PathLike[str] | dict[str, Any] | None = None,
    *,
    init: str | PathLike[str] | dict[str, Any] | None = None,
    roi: Sequence[int] | None = None,
    depth_scale: float = 0.001,
    outliers: float = 0.2,
    fix_epsilon: bool = False,
    free_space: bool = True,
    support: bool = True,
) -> Track:
    """Follows one object through ``frames`` as ``dsq track`` does, frame by frame as the
    iterable gives them: 16-bit PNG paths, PLY/OBJ paths (camera-frame clouds), or (H, W)
    arrays (uint16 in units of ``depth_scale`` metres, any other number type in metres).
    ``intrinsics`` is Open3D's camera JSON (a path or its dict); by default Open3D's PrimeSense
    camera (640×480, f = 525). The track starts from ``init`` (a ``dsq fit --out-params`` file,
    a track's line or its dict) or from a fit inside the pixel box ``roi`` (x0, y0, x1, y1) of
    the first frame. The same frames give ``dsq track``'s lines, bit for bit."""
