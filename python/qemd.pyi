"""Quadric Error Metric denoising of point clouds and meshes: numpy in, numpy out.

The keywords of :func:`denoise` and :func:`denoise_file` are the fields of the parameter spec
that ``qemd denoise`` flags and the HTTP API's JSON use (``--sigma-r`` is ``sigma_r``), with the
same defaults and the same validation messages. Every error is :class:`Error`, a ``ValueError``
with a one-line message. The GIL is released while computing; Ctrl-C stops a run with
``KeyboardInterrupt``. Results are bit-identical for any number of threads.
"""

from os import PathLike
from typing import Any, Literal, Optional, Sequence, Tuple, Union, overload

import numpy as np
import numpy.typing as npt

__version__: str

Points = Union[npt.NDArray[np.float64], npt.NDArray[np.float32]]
Faces = Union[
    npt.NDArray[np.int32], npt.NDArray[np.int64], npt.NDArray[np.uint32], npt.NDArray[np.uint64]
]
Method = Literal["qem", "bilateral"]
PlanesKind = Literal["face", "tangent"]
NormalWeighting = Literal["area", "mean"]
SolveKind = Literal["plain", "robust", "regularised", "damped"]
OutlierMode = Literal["off", "classify", "remove"]
StrPath = Union[str, "PathLike[str]"]

class Error(ValueError):
    """A refused input or parameter, or a failed run; the message is one line, as the CLI's."""

@overload
def denoise(
    points: Points,
    *,
    faces: Optional[Faces] = None,
    threads: Optional[int] = None,
    paper: Optional[bool] = None,
    method: Optional[Method] = None,
    planes: Optional[PlanesKind] = None,
    filter: Optional[int] = None,
    updates: Optional[int] = None,
    mu: Optional[float] = None,
    sigma_r: Optional[float] = None,
    volume: Optional[bool] = None,
    guard: Optional[bool] = None,
    max_move: Optional[float] = None,
    radius: Optional[float] = None,
    rings: Optional[int] = None,
    knn: Optional[int] = None,
    normals: Optional[NormalWeighting] = None,
    solve: Optional[SolveKind] = None,
    eps: Optional[float] = None,
    iterations: Optional[int] = None,
    outliers: Optional[Literal["off", "remove"]] = None,
    outlier_alpha: Optional[float] = None,
    sensor_origin: Optional[Union[str, Sequence[float]]] = None,
) -> Points: ...
@overload
def denoise(
    points: Points,
    *,
    outliers: Literal["classify"],
    faces: None = None,
    threads: Optional[int] = None,
    **params: Any,
) -> Tuple[Points, npt.NDArray[np.bool_]]: ...
def denoise(points: Points, *, faces: Optional[Faces] = None, **params: Any) -> Any:
    """Denoise a point cloud, or a triangle mesh given ``faces``.

    Parameters
    ----------
    points
        ``(N, 3)`` float64 or float32 array, C or Fortran order. float32 is computed in float64
        (with the same float64 origin rule as files) and returned as float32. A NaN, infinite or
        out-of-range (beyond ±1e12) coordinate raises.
    faces
        Optional ``(M, 3)`` integer array of vertex indices: mesh mode (k-rings and face
        planes), unless ``knn`` is given.
    threads
        Worker threads (default: all cores). The result does not depend on it.
    **params
        The spec's fields: ``knn`` (default 16 on clouds), ``method``, ``planes``, ``filter``,
        ``updates``, ``mu``, ``sigma_r``, ``volume``, ``guard``, ``max_move``, ``radius``, ``rings``,
        ``normals``, ``solve``, ``eps``, ``lambda`` (pass it as ``**{"lambda": 0.1}``: it is a
        Python keyword), ``iterations``, ``paper``, ``outliers``, ``outlier_alpha``, ``sensor_origin`` (the
        scanner's position: ``[x, y, z]``, ``"x,y,z"`` or ``"none"``; returns then move along
        their beams).
        :func:`spec_fields` lists them. ``write_normals`` applies to files
        (:func:`denoise_file`) and raises here.

    Returns
    -------
    The denoised positions in the input's dtype, one row per input row. With
    ``outliers="remove"`` the outliers' rows are left out; with ``outliers="classify"`` a tuple
    ``(points, noise)``, ``noise`` a bool ``(N,)`` array, flagged points keeping their input
    position.

    Raises
    ------
    Error
        A bad array, a bad parameter (the spec's message, e.g. ``invalid parameter
        outlier_alpha: must be finite and ≥ 0, got -1``), fewer points than ``knn``, all points
        identical.
    """

def denoise_file(
    src: StrPath,
    dst: StrPath,
    *,
    memory_budget: Optional[int] = None,
    tile_points: Optional[int] = None,
    temp_dir: Optional[StrPath] = None,
    input_format: Optional[str] = None,
    output_format: Optional[str] = None,
    threads: Optional[int] = None,
    **params: Any,
) -> dict[str, Any]:
    """Denoise the file ``src`` into ``dst``, exactly as ``qemd denoise SRC DST`` does.

    Streams the input and runs in tiles out of core when the cloud does not fit
    ``memory_budget`` (bytes, default 1 GiB) or when ``tile_points`` is given; the output keeps
    the input's schema and appears atomically; formats follow the extensions unless
    ``input_format`` / ``output_format`` name them (``ply``, ``las``, ``laz``, ``pcd``, ...).
    The other keywords are the spec's fields, as for :func:`denoise`; ``write_normals=True``
    (files only) adds each point's normal, curvature and structure class as fields, as
    ``qemd denoise --write-normals`` does.

    Returns the run report (the CLI's ``--report`` JSON) as a dict: ``mode``, ``points_in``,
    ``points_out``, ``tiles``, ``outliers_found``, ``stats``, ``phases``, ...

    Raises :class:`Error` naming the file on unreadable or malformed input, a bad parameter or a
    failed write; no output is left behind.
    """

def normals(points: Points, knn: int = 16, *, threads: Optional[int] = None) -> Points:
    """Unit PCA normals over each point's ``knn`` nearest neighbours (the point included).

    Unoriented (the sign is the PCA's); zero rows where a neighbourhood is coincident or
    collinear. Returned in the input's dtype.
    """

def knn(
    points: Points, k: int, *, threads: Optional[int] = None
) -> Tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """Exact ``k`` nearest neighbours of every point, the point itself included.

    Returns ``(indices, distances)``, both ``(N, k)``, each row ascending by (distance, index):
    the lists the denoiser uses. ``k`` must be between 1 and N.
    """

def spec_fields() -> list[str]:
    """The parameter spec's field names: the keywords :func:`denoise` accepts."""
