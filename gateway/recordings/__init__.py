"""Recording files: the reader (CSV, CSV.gz; refused whole when malformed) and the writer."""
