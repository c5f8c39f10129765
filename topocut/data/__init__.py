"""Versioned artifacts (datasets, checkpoints, evaluations) and the demonstration dataset format."""

from topocut.data.store import ArtifactRef, ArtifactStore, CorruptArtifact, MissingArtifact

__all__ = ["ArtifactStore", "ArtifactRef", "CorruptArtifact", "MissingArtifact"]
