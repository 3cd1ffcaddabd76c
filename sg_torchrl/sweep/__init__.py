"""`sg-sweep`: a grid of algorithms x env ids x seed groups run as Ray tasks, and its report."""
