"""Files calibrations leave flockcal in: BVH, skeleton JSON, HTML reports."""
