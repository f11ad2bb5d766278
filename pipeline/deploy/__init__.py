"""Deployment of the student's mask path M = [Z >= logit(tau)] (eq:inference-mask).

Export, int8, the deploy bundle, the engines, segmenting image files and the efficiency benchmark.
"""
