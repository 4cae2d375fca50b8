"""Multi-agent trajectory evaluation and the experiment runner."""
