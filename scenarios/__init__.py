"""Closed-loop scenarios and the ``pinnmpc`` command line."""
