"""Skeletons from optical marker positions alone (Kirk, O'Brien & Forsyth 2005): pure numpy/scipy."""
