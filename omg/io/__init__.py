"""Reading motion files (BVH) into clips."""
