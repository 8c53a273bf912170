"""Calibration targets: one description for chessboards, circle grids and ChArUco boards.

A :class:`Target` names a planar board once; every command that takes a board
(camera calibration, Zhou's planar-target plane calibration, the cross-ratio check)
detects it with :meth:`Target.detect`, which returns a :class:`Detection`: the ids
of the points found, their image positions (distorted px) and their board
coordinates (mm).  Partial views (ChArUco boards half hidden by the laser or a
hand) are detections with fewer ids.

Board frames (mm, z = 0 on the board, z away from the camera; see docs/targets.md):

- ``chessboard`` COLSxROWS *inner corners*, square ``s``: corner ``(i, j)`` at
  ``(i s, j s)``, id ``j·cols + i`` (OpenCV's order);
- ``circles`` COLSxROWS dots (OpenCV's symmetric grid): dot ``(i, j)`` at ``(i s, j s)``,
  ``s`` the centre pitch;
- ``acircles`` COLSxROWS (OpenCV's asymmetric grid and its sample's convention): dot
  ``(i, j)`` at ``((2i + j mod 2) s, j s)``; neighbours along a row are ``2 s`` apart;
- ``charuco`` COLSxROWS *squares*, square ``s``, marker ``m``, an ArUco dictionary: the
  board frame and corner ids of ``cv2.aruco.CharucoBoard`` (corner ``k`` of the
  ``(cols-1)x(rows-1)`` inner corners at ``((k mod (cols-1) + 1) s, (k div (cols-1) + 1) s)``).

Circle centres.  The image of a circle's centre is not the centre of its image
ellipse: under perspective the ellipse (and the dot's area centroid, which blob
detectors return) moves away from the projected centre by up to ~0.1 px on strongly
tilted boards of common size (measured: benchmarks/bench_targets.py).  Dots are
located by their darkness-weighted centroid (blur keeps a dot's first moments) and
:func:`correct_circle_centres` removes the perspective offset once a pose is known.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from lightplane.core.checks import MAX_DISTANCE_MM, integer, number
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import robust_sigma
from lightplane.core.io import to_gray8
from lightplane.camera.corners import find_board
from lightplane.core.io import to_gray_float

__all__ = ["KINDS", "MAX_BOARD_SIDE", "Target", "Detection", "as_target", "parse_target", "board_object_points",
           "correct_circle_centres", "to_gray8"]

KINDS = ("chessboard", "circles", "acircles", "charuco")
_MIN_CHARUCO_CORNERS = 6
#: the most columns or rows a target file may give
MAX_BOARD_SIDE = 1000


def board_object_points(kind: str, cols: int, rows: int, square_mm: float, ids=None) -> np.ndarray:
    """(M, 3) board coordinates (mm, z = 0) of the points ``ids`` (default: all, id order) of a
    ``kind`` board (one of :data:`KINDS`) of ``cols`` x ``rows`` inner corners, dots or ChArUco
    squares, square (centre pitch) ``square_mm``: the board frames of the module docstring.

    The one layout of every board kind: :meth:`Target.object_points` and the simulator's targets
    are this.  Lattice point ``(x, y)`` (:func:`board_lattice_index`) lies at
    ``origin + (x, y) · square_mm``, the origin ``(square_mm, square_mm)`` on a ChArUco board
    (OpenCV's ``CharucoBoard`` frame), else ``(0, 0)``.
    """
    s = square_mm if kind == "charuco" else 0.0
    xy = np.array([s, s]) + board_lattice_index(kind, cols, rows, ids) * square_mm
    return np.column_stack([xy, np.zeros(len(xy))])


def board_lattice_index(kind: str, cols: int, rows: int, ids=None) -> np.ndarray:
    """(M, 2) int lattice coordinates ``(x, y)`` of the points ``ids`` (default: all, id order) of a
    ``kind`` board of ``cols`` x ``rows``: id ``y · n + x`` with ``n`` the points per row (``cols``,
    ChArUco ``cols - 1``), staggered ``x = 2 i + y mod 2`` on an asymmetric circle grid.  The ids
    are not checked (:meth:`Target.lattice_index` does)."""
    n = cols - 1 if kind == "charuco" else cols
    ids = np.arange(n * (rows - 1 if kind == "charuco" else rows)) if ids is None \
        else np.asarray(ids, dtype=np.intp).ravel()
    i, j = ids % n, ids // n
    if kind == "acircles":
        i = 2 * i + j % 2
    return np.column_stack([i, j]).astype(np.intp)


@dataclass(frozen=True)
class Detection:
    """Points of a target found in one image.

    ids : (M,) int, point ids (see :class:`Target`); uv : (M, 2) float, distorted px;
    object_mm : (M, 3) float, the same points in the board frame (mm, z = 0);
    dark_dots : circle grids: whether the dots were found dark on a light board.
    """

    ids: np.ndarray
    uv: np.ndarray
    object_mm: np.ndarray
    dark_dots: bool = True

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class Target:
    """A planar calibration target (see the module docstring for the board frames).

    kind : one of :data:`KINDS`.  cols, rows : inner corners (chessboard), dots
    (circle grids, OpenCV's ``patternSize``) or squares (ChArUco).  square_mm : square
    size; the centre pitch for circle grids.  marker_mm, dictionary : ChArUco only
    (dictionary as OpenCV names it, e.g. ``"DICT_5X5_100"``).  dot_mm : the circles'
    diameter (circle grids; None: measured in each image).
    """

    kind: str = "chessboard"
    cols: int = 9
    rows: int = 6
    square_mm: float = 1.0
    marker_mm: float | None = None
    dictionary: str | None = None
    dot_mm: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise LightplaneError(f"board kind must be one of {', '.join(KINDS)}; got {self.kind!r}")
        object.__setattr__(self, "cols", int(self.cols))
        object.__setattr__(self, "rows", int(self.rows))
        least = 3 if self.kind == "charuco" else 2
        if self.cols < least or self.rows < least:
            what = "squares" if self.kind == "charuco" else ("inner corners" if self.kind == "chessboard" else "dots")
            raise LightplaneError(f"a {self.kind} board needs at least {least}x{least} {what}, got {self.cols}x{self.rows}")
        if max(self.cols, self.rows) > MAX_BOARD_SIDE:
            raise LightplaneError(f"a board of {self.cols}x{self.rows} is beyond what an image can hold (at most "
                                  f"{MAX_BOARD_SIDE} along a side)")
        if not (np.isfinite(self.square_mm) and self.square_mm > 0):
            raise LightplaneError(f"the square size (--square) must be positive, got {self.square_mm} mm")
        if self.kind == "charuco":
            if self.marker_mm is None or not (0 < self.marker_mm < self.square_mm):
                raise LightplaneError(f"a charuco board needs a marker size (--marker) between 0 and the square "
                                      f"size {self.square_mm} mm, got {self.marker_mm}")
            object.__setattr__(self, "dictionary", _dictionary_name(self.dictionary or "DICT_4X4_50"))
        if self.dot_mm is not None and not (0 < self.dot_mm < self.spacing_mm):
            raise LightplaneError(f"the dot diameter must be between 0 and the dot spacing {self.spacing_mm:.3g} mm, "
                                  f"got {self.dot_mm}")

    # ------------------------------------------------------------------ geometry
    @property
    def n_points(self) -> int:
        """Number of points of a complete view."""
        if self.kind == "charuco":
            return (self.cols - 1) * (self.rows - 1)
        return self.cols * self.rows

    @property
    def spacing_mm(self) -> float:
        """Distance between nearest neighbour points (mm)."""
        return self.square_mm * (np.sqrt(2.0) if self.kind == "acircles" else 1.0)

    @property
    def partial_views(self) -> bool:
        """Whether a view may show only some of the points (ChArUco)."""
        return self.kind == "charuco"

    @property
    def min_points(self) -> int:
        """Fewest points of a usable view."""
        return _MIN_CHARUCO_CORNERS if self.partial_views else self.n_points

    def lattice_index(self, ids=None) -> np.ndarray:
        """(M, 2) int lattice coordinates ``(x, y)`` of the points: board position
        ``lattice_origin_mm + (x, y) · square_mm``.  Rows (equal y) and columns (equal x)
        of the lattice are straight lines of points (the cross-ratio check uses them)."""
        return board_lattice_index(self.kind, self.cols, self.rows, self._checked_ids(ids))

    def _checked_ids(self, ids) -> np.ndarray:
        """``ids`` as an (M,) int array (None: all, id order); LightplaneError outside the board."""
        ids = np.arange(self.n_points) if ids is None else np.asarray(ids, dtype=np.intp).ravel()
        if ids.size and (ids.min() < 0 or ids.max() >= self.n_points):
            raise LightplaneError(f"point ids must be in 0..{self.n_points - 1} for {self.describe()}")
        return ids

    @property
    def lattice_shape(self) -> tuple[int, int]:
        """(nx, ny): extent of :meth:`lattice_index`."""
        if self.kind == "charuco":
            return self.cols - 1, self.rows - 1
        if self.kind == "acircles":
            return 2 * self.cols, self.rows
        return self.cols, self.rows

    @property
    def lattice_origin_mm(self) -> np.ndarray:
        """Board position (mm) of lattice point (0, 0)."""
        s = self.square_mm if self.kind == "charuco" else 0.0
        return np.array([s, s])

    def object_points(self, ids=None) -> np.ndarray:
        """(M, 3) board coordinates (mm, z = 0) of the points ``ids`` (default: all, id order):
        :func:`board_object_points`."""
        return board_object_points(self.kind, self.cols, self.rows, self.square_mm, self._checked_ids(ids))

    def outline_mm(self) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)`` board rectangle (mm) sure to be printed target: stripe points are taken
        inside it.  Chessboard: the inner corners grown by 0.9 square (the outer squares reach one square
        beyond); circle grids: the outer dots' centres grown by half the spacing; ChArUco: the squares."""
        if self.kind == "charuco":
            return 0.0, self.cols * self.square_mm, 0.0, self.rows * self.square_mm
        p = self.object_points()
        m = 0.9 * self.square_mm if self.kind == "chessboard" else 0.5 * self.spacing_mm
        return float(p[:, 0].min() - m), float(p[:, 0].max() + m), float(p[:, 1].min() - m), float(p[:, 1].max() + m)

    def describe(self) -> str:
        """One line for people, with units."""
        if self.kind == "chessboard":
            return f"chessboard {self.cols}x{self.rows} inner corners, {self.square_mm:g} mm squares"
        if self.kind == "charuco":
            return (f"charuco {self.cols}x{self.rows} squares, {self.square_mm:g} mm squares, "
                    f"{self.marker_mm:g} mm markers, {self.dictionary}")
        kind = "symmetric" if self.kind == "circles" else "asymmetric"
        dot = f", {self.dot_mm:g} mm dots" if self.dot_mm else ""
        return f"{kind} circle grid {self.cols}x{self.rows} dots, {self.square_mm:g} mm pitch{dot}"

    @property
    def spec(self) -> str:
        """The command-line form ``KIND:COLSxROWS``."""
        return f"{self.kind}:{self.cols}x{self.rows}"

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}

    @classmethod
    def from_dict(cls, d: dict, where: str = "target") -> "Target":
        known = {"kind", "cols", "rows", "square_mm", "marker_mm", "dictionary", "dot_mm"}
        if not isinstance(d, dict):
            raise LightplaneError(f"{where}: a target must be a JSON object")
        d = dict(d)
        if "board" in d and "cols" not in d:  # "board": "charuco:11x8"
            board = d.pop("board")
            if not isinstance(board, str):
                raise LightplaneError(f"{where}: field 'board' must be KIND:COLSxROWS, got {board!r:.40}")
            t = parse_target(board, 1.0)
            d.update(kind=t.kind, cols=t.cols, rows=t.rows)
        extra = set(d) - known
        if extra:
            raise LightplaneError(f"{where}: unknown target field(s) {', '.join(sorted(map(str, extra)))} "
                                  f"(known: {', '.join(sorted(known))})")
        for k in ("cols", "rows", "square_mm"):
            if k not in d:
                raise LightplaneError(f"{where}: the target needs {k!r}")
        for k in ("cols", "rows"):
            d[k] = integer(d[k], k, where, lo=1, hi=MAX_BOARD_SIDE)
        for k in ("square_mm", "marker_mm", "dot_mm"):
            if d.get(k) is not None:
                d[k] = number(d[k], k, where, positive=True, hi=MAX_DISTANCE_MM)
        for k in ("kind", "dictionary"):
            if d.get(k) is not None and not isinstance(d[k], str):
                raise LightplaneError(f"{where}: field '{k}' must be a name, got {d[k]!r:.40}")
        try:
            return cls(**d)
        except (TypeError, ValueError) as e:
            raise LightplaneError(f"{where}: {e}") from None

    @classmethod
    def load(cls, path) -> "Target":
        """A target file (JSON): ``{"kind": "charuco", "cols": 11, "rows": 8, "square_mm": 15,
        "marker_mm": 11, "dictionary": "DICT_5X5_100"}``; a result file with a ``"target"`` entry works too."""
        p = Path(path)
        try:
            d = json.loads(p.read_text())
        except FileNotFoundError:
            raise LightplaneError(f"{p}: no such file") from None
        except (OSError, ValueError, RecursionError) as e:  # ValueError: undecodable bytes, bad JSON, huge ints
            raise LightplaneError(f"{p}: not a target file ({_first_line(e)})") from None
        if isinstance(d, dict) and isinstance(d.get("target"), dict):
            d = d["target"]
        return cls.from_dict(d, str(p))

    # ------------------------------------------------------------------ detection
    def detect(self, image: np.ndarray, *, refine: bool | str = False) -> Detection | None:
        """Find the target in one image (gray or BGR, 8/16-bit or float): a :class:`Detection` or None.

        Chessboard: :func:`lightplane.camera.corners.find_board` (``findChessboardCornersSB``,
        ``cornerSubPix``, with ``refine`` the saddle fit).  Circle grids: ``findCirclesGrid``
        with blob parameters for dark dots on light, then light dots on dark, each centre
        refined to its darkness-weighted centroid (no perspective correction: see
        :func:`correct_circle_centres`).  ChArUco: ``cv2.aruco.CharucoDetector`` (corners
        interpolated from the markers and refined by OpenCV); a view with fewer than 6
        corners, or with all its corners on one line, is not usable (None).
        """
        if self.kind == "chessboard":
            c = find_board(image, (self.cols, self.rows), refine=refine)
            if c is None:
                return None
            ids = np.arange(self.n_points)
            return Detection(ids, c, self.object_points(ids))
        gray = to_gray8(image)
        if self.kind == "charuco":
            return self._detect_charuco(gray)
        return self._detect_circles(gray, image)

    def cv_board(self):
        """The ``cv2.aruco.CharucoBoard`` of a ChArUco target."""
        import cv2

        if self.kind != "charuco":
            raise LightplaneError(f"{self.describe()} is not a charuco board")
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), float(self.square_mm), float(self.marker_mm), d)

    def _detect_charuco(self, gray: np.ndarray) -> Detection | None:
        import cv2

        det = cv2.aruco.CharucoDetector(self.cv_board())
        corners, ids, _, _ = det.detectBoard(gray)
        if corners is None or ids is None or len(ids) < _MIN_CHARUCO_CORNERS:
            return None
        ids = ids.ravel().astype(np.intp)
        order = np.argsort(ids)
        ids = ids[order]
        uv = corners.reshape(-1, 2)[order].astype(np.float64)
        lat = self.lattice_index(ids)
        if np.linalg.matrix_rank(lat - lat.mean(axis=0), tol=1e-9) < 2:  # collinear: no pose
            return None
        obj = self.object_points(ids)
        # OpenCV's interpolated corners move by up to ~0.5 px under cornerSubPix: refine them, with a
        # window that stays inside the white gap between a corner and the nearest marker's edge
        H, _ = cv2.findHomography(obj[:, :2], uv, 0)
        if H is not None:
            assert self.marker_mm is not None  # a charuco target has its marker size (checked on construction)
            J = _jacobians(H, obj[:, :2])
            px_per_mm = float(np.median(np.sqrt(np.abs(np.linalg.det(J)))))
            gap_px = 0.5 * (self.square_mm - self.marker_mm) * px_per_mm
            half = int(np.floor(min(0.3 * self.square_mm * px_per_mm, 0.85 * gap_px, 11)))
            if half >= 2:
                crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
                ref = cv2.cornerSubPix(gray, uv.astype(np.float32).reshape(-1, 1, 2), (half, half), (-1, -1),
                                       crit).reshape(-1, 2).astype(np.float64)
                ok = np.linalg.norm(ref - uv, axis=1) < 0.5 * half
                uv[ok] = ref[ok]
        return Detection(ids, uv, obj)

    def _detect_circles(self, gray: np.ndarray, image: np.ndarray) -> Detection | None:
        import cv2

        flags = cv2.CALIB_CB_SYMMETRIC_GRID if self.kind == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
        h, w = gray.shape
        tries = [(colour, extra) for colour in (0, 255) for extra in (0, cv2.CALIB_CB_CLUSTERING)]
        for colour, extra in tries:  # dark dots on a light board, then light on dark; clustering for steep views
            # SimpleBlobDetector_Params exists at runtime (OpenCV 4.x and 5.x); the stubs only know the nested name
            p = cv2.SimpleBlobDetector_Params()  # type: ignore[attr-defined]
            p.filterByColor, p.blobColor = True, colour
            p.minArea, p.maxArea = 8.0, 0.25 * h * w / self.n_points
            p.filterByCircularity, p.minCircularity = True, 0.5  # tilted dots are ellipses
            p.filterByConvexity, p.minConvexity = True, 0.85
            p.filterByInertia, p.minInertiaRatio = True, 0.05
            p.minDistBetweenBlobs = 3.0
            found, centres = cv2.findCirclesGrid(gray, (self.cols, self.rows), flags=flags | extra,
                                                 blobDetector=cv2.SimpleBlobDetector.create(p))
            if found and centres is not None and len(centres) == self.n_points:
                c = self._grid_order(centres.reshape(-1, 2).astype(np.float64))
                if c is None:
                    continue
                ids = np.arange(self.n_points)
                uv = _dot_centroids(image, c, self, dark=colour == 0)
                return Detection(ids, uv, self.object_points(ids), dark_dots=colour == 0)
        return None

    def _grid_order(self, uv: np.ndarray) -> np.ndarray | None:
        """``findCirclesGrid``'s centres in id order, or None when no ordering fits the board.

        An asymmetric grid with an even number of rows looks the same turned by 180°, and
        OpenCV then numbers it in an order that is no view of the board (row pairs swapped):
        such an order is recognised by its homography residual and renumbered.  A mirrored
        numbering (a homography that turns the board over) is refused."""
        import cv2

        def fits(c):
            H, _ = cv2.findHomography(self.object_points()[:, :2], c, 0)
            if H is None:
                return False
            # seen from the front (board z away from the camera) the board's x, y turn as the image's
            # u, v: a mirrored numbering fits a homography too, but with the other orientation
            if np.linalg.det(_jacobians(H, self.object_points()[:1, :2])[0]) <= 0:
                return False
            p = cv2.perspectiveTransform(self.object_points()[:, :2].reshape(-1, 1, 2), H).reshape(-1, 2)
            spacing = np.median(np.linalg.norm(np.diff(c, axis=0), axis=1))
            return np.sqrt(np.mean(np.sum((p - c) ** 2, axis=1))) < 0.1 * spacing

        if fits(uv):
            return uv
        if self.kind == "circles":  # mirrored numbering of a symmetric grid: read each row backwards
            c = uv.reshape(self.rows, self.cols, 2)[:, ::-1].reshape(-1, 2)
            if fits(c):
                return c
        if self.kind == "acircles" and self.rows % 2 == 0:
            grid = uv.reshape(self.rows, self.cols, 2)
            j = np.arange(self.rows)
            src = np.where(j % 2 == 0, self.rows - 2 - j, self.rows - j)  # the detected row holding board row j
            c = grid[src, ::-1].reshape(-1, 2)
            if fits(c):
                return c
        return None


def as_target(board, square_mm: float | None = None) -> Target:
    """A :class:`Target` as it is, or a chessboard from ``(cols, rows)`` inner corners and ``square_mm``."""
    if isinstance(board, Target):
        if square_mm is not None and not np.isclose(square_mm, board.square_mm):
            raise LightplaneError(f"square_mm {square_mm} differs from the target's {board.square_mm} mm")
        return board
    try:
        cols, rows = (int(v) for v in board)
    except (TypeError, ValueError):
        raise LightplaneError(f"board must be a Target or (cols, rows), got {board!r}") from None
    if square_mm is None:
        raise LightplaneError("a (cols, rows) board needs square_mm")
    return Target("chessboard", cols, rows, float(square_mm))


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def _dictionary_name(name: str) -> str:
    import cv2

    n = str(name).strip().upper()
    n = n if n.startswith("DICT_") else "DICT_" + n
    if not isinstance(getattr(cv2.aruco, n, None), int):
        names = sorted(k for k in dir(cv2.aruco) if k.startswith("DICT_"))
        raise LightplaneError(f"unknown ArUco dictionary {name!r}; one of {', '.join(names)}")
    return n


def _local_jacobians(target: Target, uv: np.ndarray) -> np.ndarray:
    """(N, 2, 2) d(uv)/d(board mm) at each point, from a homography through all of them."""
    import cv2

    obj = target.object_points()[:, :2]
    H, _ = cv2.findHomography(obj, uv, 0)
    if H is None:
        return np.tile(np.eye(2), (len(uv), 1, 1))
    return _jacobians(H, obj)


def _jacobians(H: np.ndarray, obj: np.ndarray) -> np.ndarray:
    """(N, 2, 2) derivative of the homography ``H`` (board mm -> px) at the board points ``obj`` (N, 2)."""
    X = np.column_stack([obj, np.ones(len(obj))])
    p = X @ H.T  # (N, 3)
    w = p[:, 2:3]
    J = (H[None, :2, :2] * w[:, :, None] - p[:, :2, None] * H[None, 2:3, :2]) / (w[:, :, None] ** 2)
    return J


def _dot_window(g: np.ndarray, c: np.ndarray, J: np.ndarray, R: float):
    """Pixels of the image of a disc of radius ``R`` (board mm) centred on the dot at ``c`` (px), through
    the local Jacobian ``J`` (2, 2): ``(x, y, values)`` of those pixels, or None when the window
    leaves the image or ``J`` is singular."""
    try:
        Jinv = np.linalg.inv(J)
    except np.linalg.LinAlgError:
        return None
    half = int(np.ceil(R * np.abs(J).sum(axis=1).max())) + 1
    x0, y0 = int(round(c[0])) - half, int(round(c[1])) - half
    x1, y1 = x0 + 2 * half + 1, y0 + 2 * half + 1
    if x0 < 0 or y0 < 0 or x1 > g.shape[1] or y1 > g.shape[0]:
        return None
    yy, xx = np.mgrid[y0:y1, x0:x1]
    d = np.stack([xx - c[0], yy - c[1]], axis=-1) @ Jinv.T  # board mm offsets
    inside = (d ** 2).sum(axis=-1) <= R * R
    return xx[inside], yy[inside], g[y0:y1, x0:x1][inside].astype(np.float64)


def _dot_centroids(image: np.ndarray, uv0: np.ndarray, target: Target, *, dark: bool,
                   iterations: int = 3) -> np.ndarray:
    """Darkness- (or brightness-) weighted centroid of each dot, ``(N, 2)`` px.

    The window around each dot is the image of a disc of 0.46 spacings on the board
    (:func:`_dot_window`, through the local Jacobian of a homography fitted to all dots), so
    it holds the whole blurred dot and none of its neighbours at any tilt.  Weights are the
    contrast to the board's level there (a plane fitted to the window's board pixels, so
    shading and vignetting do not pull the centre), divided by that level (shading scales
    the dot's contrast too), and zero below three times the board's noise.  A blurred dot's
    weighted centroid is its area centroid: blur is a convolution with a centred kernel and
    keeps first moments.
    """
    g = to_gray_float(image)
    J = _local_jacobians(target, uv0)
    R = 0.46 * target.spacing_mm
    out = uv0.copy()
    for k in range(len(uv0)):
        c = uv0[k].copy()
        for _ in range(iterations):
            win = _dot_window(g, c, J[k], R)
            if win is None or win[2].size < 9:
                break
            xs, ys, vals = win
            # the board's level around the dot as a plane (shading and vignetting tilt it), fitted to
            # the board pixels of the window; its noise sets the threshold below which a pixel is board
            lo, hi = np.percentile(vals, [5, 95])
            board = (vals > 0.5 * (lo + hi)) if dark else (vals < 0.5 * (lo + hi))
            if board.sum() < 6:
                break
            X = np.column_stack([np.ones(vals.size), xs - c[0], ys - c[1]])
            coef, *_ = np.linalg.lstsq(X[board], vals[board], rcond=None)
            level = X @ coef
            noise = robust_sigma(vals[board] - level[board])
            contrast = (level - vals) if dark else (vals - level)
            # shading multiplies the dot's contrast too: divide by the local illumination (the board's
            # level for dark dots, the dot's for light ones) so the weights are the albedo step alone
            light = level if dark else level + (hi - lo)
            wgt = np.where(contrast > max(3.0 * noise, 0.02 * abs(hi - lo)), contrast / np.maximum(light, 1e-6), 0.0)
            total = wgt.sum()
            if not total > 0:
                break
            new = np.array([(wgt * xs).sum() / total, (wgt * ys).sum() / total])
            if not np.all(np.isfinite(new)) or np.linalg.norm(new - uv0[k]) > 0.5 * R * np.abs(J[k]).max():
                break
            done = np.linalg.norm(new - c) < 1e-3
            c = new
            if done:
                break
        out[k] = c
    return out


def dot_diameter_mm(image: np.ndarray, det: Detection, target: Target) -> float:
    """The dots' diameter (mm): ``target.dot_mm`` when given, else measured in one image, the
    median over dots of the dot's area (pixels beyond the mid-level between dot and board, dark
    or light as the detection found them) in :func:`_dot_window`'s disc."""
    if target.dot_mm:
        return float(target.dot_mm)
    g = to_gray_float(image)
    J = _local_jacobians(target, det.uv)
    R = 0.46 * target.spacing_mm
    diam = []
    for k, c in enumerate(det.uv):
        win = _dot_window(g, c, J[k], R)
        if win is None:
            continue
        vals = win[2]
        hi, lo = np.percentile(vals, [90, 5]) if det.dark_dots else np.percentile(vals, [95, 10])
        mid = 0.5 * (hi + lo)
        frac = np.mean(vals < mid) if det.dark_dots else np.mean(vals > mid)
        diam.append(2.0 * R * np.sqrt(frac))  # dot area / window area = (r / R)^2 on the board
    if not diam:
        return 0.5 * target.spacing_mm
    return float(np.median(diam))


def correct_circle_centres(camera, target: Target, uv: np.ndarray, ids, R_cam_board: np.ndarray,
                           t_cam_board: np.ndarray, dot_mm: float) -> np.ndarray:
    """Dot centres moved from the dots' area centroids to the projections of the circles' centres, (M, 2) px.

    For each dot of diameter ``dot_mm`` at the pose ``(R_cam_board, t_cam_board)`` the
    circle's rim is projected (with distortion, 96 points) and the area centroid of
    that polygon compared with the projected centre; their difference, the
    perspective offset, is taken off the measured centroid ``uv``.
    """
    obj = target.object_points(ids)
    a = np.linspace(0.0, 2.0 * np.pi, 96, endpoint=False)
    r = 0.5 * float(dot_mm)
    rim = obj[:, None, :] + r * np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=-1)[None]
    p_cam = rim.reshape(-1, 3) @ np.asarray(R_cam_board).T + np.asarray(t_cam_board)
    poly = camera.project(p_cam).reshape(len(obj), len(a), 2)
    x, y = poly[..., 0], poly[..., 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cr = x * yn - xn * y
    A = cr.sum(axis=1) / 2.0
    cx = ((x + xn) * cr).sum(axis=1) / (6.0 * A)
    cy = ((y + yn) * cr).sum(axis=1) / (6.0 * A)
    centre = camera.project(obj @ np.asarray(R_cam_board).T + np.asarray(t_cam_board))
    return np.asarray(uv, dtype=np.float64) - (np.column_stack([cx, cy]) - centre)


def parse_target(text: str | None, square_mm: float | None, *, marker_mm: float | None = None,
                 dictionary: str | None = None, dot_mm: float | None = None, target_file=None) -> Target:
    """The command line's board: ``--board KIND:COLSxROWS --square MM`` (KIND chessboard by default,
    circles, acircles or charuco with ``--marker MM --dictionary NAME``) or ``--target FILE.json``."""
    if target_file is not None:
        if text is not None:
            raise LightplaneError("give either --board/--square or --target, not both")
        return Target.load(target_file)
    if text is None:
        raise LightplaneError("give the board: --board KIND:COLSxROWS --square MM, or --target FILE.json")
    kind, _, size = str(text).strip().lower().rpartition(":")
    kind = kind or "chessboard"
    if kind not in KINDS:
        raise LightplaneError(f"--board kind must be one of {', '.join(KINDS)}; got {kind!r} in {text!r}")
    try:
        cols, rows = (int(t) for t in size.split("x"))
    except ValueError:
        raise LightplaneError(f"--board must look like KIND:COLSxROWS, e.g. 9x6 or charuco:11x8; got {text!r}") from None
    if square_mm is None:
        raise LightplaneError("--square MM is needed with --board (square size; the centre pitch of circle grids)")
    if kind != "charuco" and (marker_mm is not None or dictionary is not None):
        raise LightplaneError(f"--marker and --dictionary are for charuco boards, not {kind}")
    if kind not in ("circles", "acircles") and dot_mm is not None:
        raise LightplaneError(f"--dot is for circle grids, not {kind}")
    return Target(kind, cols, rows, float(square_mm), marker_mm, dictionary, dot_mm)
