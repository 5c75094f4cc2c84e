"""MJCF models of the domains, installed as the package data ``tasks.mjcf``."""
