"""Geometric verification of loop candidates against the LiDAR (registration with small_gicp)."""
from .clouds import CloudStore, compact_cloud
from .config import CloudConfig, VerifierConfig
from .verifier import ACCEPTED, REJECT_REASONS, GeometricVerifier, PreparedCloud, Verification

__all__ = ["ACCEPTED", "REJECT_REASONS", "CloudConfig", "CloudStore", "GeometricVerifier", "PreparedCloud",
           "Verification", "VerifierConfig", "compact_cloud"]
