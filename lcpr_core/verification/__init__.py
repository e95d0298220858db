"""Geometric verification of loop candidates against the LiDAR (registration with small_gicp)."""
from .clouds import CloudStore, compact_cloud
from .config import CloudConfig, VerifierConfig
from .submap import SUBMAP_MODES, Submap, SubmapConfig, build_submap
from .verifier import ACCEPTED, REJECT_REASONS, GeometricVerifier, PreparedCache, PreparedCloud, Verification

__all__ = ["ACCEPTED", "REJECT_REASONS", "SUBMAP_MODES", "CloudConfig", "CloudStore", "GeometricVerifier",
           "PreparedCache", "PreparedCloud", "Submap", "SubmapConfig", "Verification", "VerifierConfig", "build_submap",
           "compact_cloud"]
