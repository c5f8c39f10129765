"""Score-entropy discrete diffusion (SEDD) over per-point labels: graph, noise, loss, sampler."""
from topocut.policies.diffusion.graph import Absorbing, Graph, Uniform, build_graph, sample_categorical
from topocut.policies.diffusion.loss import dse_loss, get_loss, sq_score_loss
from topocut.policies.diffusion.noise import GeometricNoise, LogLinearNoise, Noise, build_noise
from topocut.policies.diffusion.sampler import sample

__all__ = ["Absorbing", "Graph", "Uniform", "build_graph", "sample_categorical", "dse_loss", "sq_score_loss",
           "get_loss", "GeometricNoise", "LogLinearNoise", "Noise", "build_noise", "sample"]
