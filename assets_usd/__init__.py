"""The shipped USD asset library (hand and objects) and its manifest."""
