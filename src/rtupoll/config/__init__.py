"""What the user wrote: YAML with line marks, the profile library, site files, address plans."""
