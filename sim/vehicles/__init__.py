"""Vehicles as data (one parameter file per vehicle, ``*.toml`` here) and their rotors."""
