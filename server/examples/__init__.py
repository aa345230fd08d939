"""Small runnable examples of the learning core."""
