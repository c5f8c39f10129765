"""Versioned artifacts (datasets, checkpoints, evaluations) and the demonstration dataset format."""

from topocut.data.store import ArtifactStore, ArtifactRef, CorruptArtifact, MissingArtifact

__all__ = ["ArtifactStore", "ArtifactRef", "CorruptArtifact", "MissingArtifact"]
