"""Pictures for people: colour maps of depth and std, and figures with a colour bar."""
