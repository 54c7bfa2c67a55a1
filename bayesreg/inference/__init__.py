"""From a prepared problem and a config to what the sampler runs: the log-density targets,
the posterior mode, the chains' starts and proposal scales.
"""
