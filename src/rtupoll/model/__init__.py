"""What a device is: profiles, the codec, block planning, and the meaning of raw words."""
