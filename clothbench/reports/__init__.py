"""What people read: terminal tables, progress bars, and (later) plots."""
