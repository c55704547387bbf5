"""Workflow files, the caching runner and the command-line interface."""
