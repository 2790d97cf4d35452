"""Recording formats: recognition by content (sniff), CSV text, and device files through their readers."""
