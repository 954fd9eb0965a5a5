"""iPhUMI: phone-recorded demonstrations as training data and as live behavior prompts."""
