"""Bring-up of the PMA testbed: launch files and the end-to-end demo."""
