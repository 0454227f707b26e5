"""The mapper's parameters: a light module (no scipy, no OpenCV), so configs and the command
line can name them without loading the mapper."""

from __future__ import annotations

from dataclasses import dataclass

from tidee.agent.mapping.geometry import MIN_DEPTH


def _cells_per(length: float, cell: float, what: str) -> int:
    n = length / cell
    if abs(n - round(n)) > 1e-6 or round(n) < 1:
        raise ValueError(f"{what}: {length} m is not a whole number of {cell} m cells")
    return int(round(n))


def wants_carving(mode: str, depth: str) -> bool:
    """Whether the map carves free space (``AgentConfig.carve``): "on" always, "auto" when depth
    is estimated from RGB (its errors scatter points in front of and behind every surface), "off"
    never."""
    return mode == "on" or (mode == "auto" and depth == "estimated")


@dataclass
class MapConfig:
    """Mapping parameters (metres unless noted). Defaults give 256x256 2D maps at 5 cm and a
    128x128x64 voxel grid (10 cm x 10 cm x 5 cm), as in the paper."""

    map_size_m: float = 12.8  # square map side, centred on the start pose
    nav_cell: float = 0.05  # 2D map cell edge
    voxel_xy: float = 0.1  # voxel edge along x and y
    voxel_z: float = 0.05  # voxel edge along z
    voxel_z_range: tuple[float, float] = (-0.1, 3.1)  # heights covered by the voxel grid
    obstacle_z: tuple[float, float] = (0.1, 1.8)  # points with z in [lo, hi) are obstacles
    floor_z: float = 0.06  # points with z below this are floor (free)
    explored_threshold: int = 1  # frames with a point before a cell is explored
    max_depth: float = 8.0  # farther depths are ignored
    stride: int = 2  # pixel subsampling for the maps (not for objects)
    semantic_sigma_voxels: float = 1.5  # Gaussian dilation of centroids, in xy voxels
    agent_free_radius: float = 0.15  # disc kept free around each believed position
    # free-space carving: a cell is an obstacle only while, in one carve_z slab of the obstacle
    # band, the frames with a point outnumber the frames whose rays passed through it short of
    # their point, and number at least carve_min_hits (for noisy depth: one bad frame's points
    # do not wall the agent in for good); off: one point makes an obstacle for good
    carve: bool = False
    carve_stride: int = 4  # pixel subsampling of the carving rays
    carve_z: float = 0.1  # carving counts per cell and slab of the obstacle band this high
    carve_min_hits: int = 3  # carving: frames with a point in a slab before it is an obstacle
    merge_distance: float = 1.0  # object memory: same label within this merges
    # object memory: passable (pickupable) labels merge within this instead (None: merge_distance);
    # the rearrangement agent's: two apples on one counter are two objects to put back
    small_merge_distance: float | None = None
    box_merge: str = "union"  # object memory: 3D boxes of merged views (mean | union)
    min_object_points: int = 5  # detections with fewer valid pixels are skipped
    max_object_points: int = 4096  # pixels used for an object's box (subsampled)

    def __post_init__(self) -> None:
        self.voxel_z_range = (float(self.voxel_z_range[0]), float(self.voxel_z_range[1]))
        self.obstacle_z = (float(self.obstacle_z[0]), float(self.obstacle_z[1]))
        for name in (
            "map_size_m",
            "nav_cell",
            "voxel_xy",
            "voxel_z",
            "merge_distance",
            "small_merge_distance",
            "carve_z",
        ):
            if name == "small_merge_distance" and self.small_merge_distance is None:
                continue
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"MapConfig.{name} must be > 0, got {getattr(self, name)}")
        _cells_per(self.map_size_m, self.nav_cell, "MapConfig.map_size_m / nav_cell")
        _cells_per(self.map_size_m, self.voxel_xy, "MapConfig.map_size_m / voxel_xy")
        lo, hi = self.voxel_z_range
        if not lo < hi:
            raise ValueError(
                f"MapConfig.voxel_z_range must be (lo, hi) with lo < hi, got {self.voxel_z_range}"
            )
        _cells_per(hi - lo, self.voxel_z, "MapConfig.voxel_z_range / voxel_z")
        if not self.obstacle_z[0] < self.obstacle_z[1]:
            raise ValueError(f"MapConfig.obstacle_z must be (lo, hi) with lo < hi, got {self.obstacle_z}")
        if not self.floor_z <= self.obstacle_z[0]:
            raise ValueError(
                f"MapConfig.floor_z ({self.floor_z}) must not exceed obstacle_z[0] ({self.obstacle_z[0]})"
            )
        if int(self.explored_threshold) < 1:
            raise ValueError(f"MapConfig.explored_threshold must be >= 1, got {self.explored_threshold}")
        if not self.max_depth > MIN_DEPTH:
            raise ValueError(f"MapConfig.max_depth must be > {MIN_DEPTH} m, got {self.max_depth}")
        if int(self.stride) < 1:
            raise ValueError(f"MapConfig.stride must be >= 1, got {self.stride}")
        if int(self.carve_min_hits) < 1:
            raise ValueError(f"MapConfig.carve_min_hits must be >= 1, got {self.carve_min_hits}")
        if int(self.carve_stride) < 1:
            raise ValueError(f"MapConfig.carve_stride must be >= 1, got {self.carve_stride}")
        if self.semantic_sigma_voxels < 0:
            raise ValueError(
                f"MapConfig.semantic_sigma_voxels must be >= 0, got {self.semantic_sigma_voxels}"
            )
        if self.agent_free_radius < 0:
            raise ValueError(f"MapConfig.agent_free_radius must be >= 0, got {self.agent_free_radius}")
        if int(self.min_object_points) < 1 or int(self.max_object_points) < int(self.min_object_points):
            raise ValueError(
                f"MapConfig needs 1 <= min_object_points <= max_object_points, got "
                f"{self.min_object_points}, {self.max_object_points}"
            )

    @property
    def nav_shape(self) -> tuple[int, int]:
        n = _cells_per(self.map_size_m, self.nav_cell, "nav")
        return n, n

    @property
    def voxel_shape(self) -> tuple[int, int, int]:
        n = _cells_per(self.map_size_m, self.voxel_xy, "voxel")
        nz = _cells_per(self.voxel_z_range[1] - self.voxel_z_range[0], self.voxel_z, "voxel z")
        return n, n, nz
