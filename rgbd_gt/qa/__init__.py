"""Checking an alignment by eye and by number: edges of the photo against edges of the scan."""
