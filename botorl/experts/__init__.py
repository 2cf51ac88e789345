"""Expert policies that botorl trains to make offline data (the goal-reaching ant behind the antmaze data)."""
