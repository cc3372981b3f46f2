"""3D views of runs in the browser (viser): finished run folders and live sessions."""
