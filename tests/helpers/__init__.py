"""What several test modules share besides oracles: the suite's environment, small scenes,
toy training states and golden configurations."""
