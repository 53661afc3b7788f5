"""The workflow's entry points (thin: read inputs, call one library function, write the outputs the rule names)."""
