"""Mitsuba sensors: realistic_lens (exact) and neural_lens."""
