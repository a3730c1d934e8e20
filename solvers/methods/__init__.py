"""Fit methods: equation error, output error (single and multiple shooting), online estimators."""
