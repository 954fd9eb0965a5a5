"""Rolling out policies in benchmarks and scoring them."""
