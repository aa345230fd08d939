"""Learners: soft value iteration and its gradients, the A-SABL feedback model, BAM and its
baselines."""
