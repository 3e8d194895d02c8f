"""Graph reconstruction: each representation back to one lane graph (Path2Graph, Piece2Graph,
Pixel2Graph); `cli roundtrip` (benchmark/roundtrip.py) runs the ground truth through each and back."""
