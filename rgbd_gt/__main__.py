from rgbd_gt.cli import main

main()
