"""Model code: plain torch modules, free of Lightning and distributed logic."""
