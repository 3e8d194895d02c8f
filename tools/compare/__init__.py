"""Our metrics against the published code they follow (CGNet's evaluator, OpenLane-V2's evaluation), run
outside CI against those codebases' own checkouts."""
