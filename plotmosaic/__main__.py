from plotmosaic.cli import main

main()
