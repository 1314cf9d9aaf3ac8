"""Jobs: one function per command from plain inputs to a typed result; nothing here prints."""
