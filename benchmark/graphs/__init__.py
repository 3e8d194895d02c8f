"""Graph reconstruction: each representation back to one lane graph (Path2Graph, Piece2Graph,
Pixel2Graph), and `cli roundtrip`, the ground truth through each and back."""
