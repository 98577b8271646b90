"""What a person or a script sees: the live table and the output records."""
