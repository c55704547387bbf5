"""Proper motions: epoch matching, alignment, motion fits and accuracy reports."""
