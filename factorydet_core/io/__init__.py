"""Reading and writing point clouds and data sets."""
