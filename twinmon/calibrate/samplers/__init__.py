"""The samplers (``calibrate.sampler``): :mod:`.openturns` (OpenTURNS' Metropolis-Hastings and
Gibbs, one task per chain: the reference) and the numpy ones that move every chain of many
units at once: :mod:`.vectorised` (the sequential method) and :mod:`.joint_vectorised` (the
joint method), both predicting through :mod:`.gpbatch`.
"""
