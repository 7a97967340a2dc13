"""What people read: terminal tables and progress, README's tables, the sweep's and studies'
figures, the HTML report, renders and exports of the cloth."""
