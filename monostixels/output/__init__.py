"""What comes out: figures, the bird's-eye view, 3D stixels, the Rerun recording and files (images, depth, point clouds)."""
